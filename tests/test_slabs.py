"""Slabs of detector rows: the row-subset reader, slab plans, ownership and stitching, seams, resume."""

import h5py
import numpy as np
import pytest

from bubsub.core import MeshProjector, ScanGeometry, sphere_surface
from bubsub.core.io.scanfile import Scan, read_scan, write_scan


def _parallel(rows=24, cols=32, n=6, pixel=0.1):
    return ScanGeometry.parallel(np.linspace(0, np.pi, n, endpoint=False), pixel_size=pixel, cols=cols, rows=rows)


# -- the row-subset reader ------------------------------------------------------------------
def test_rows_reads_a_hyperslab_whose_geometry_projects_the_same(tmp_path):
    g = _parallel()
    bubble = sphere_surface([0.2, -0.1, 0.35], 0.4, attenuation=-0.1)
    data = MeshProjector(g).forward([bubble])
    rng = np.random.default_rng(1)
    background = rng.uniform(0, 1, g.shape).astype(np.float32)
    write_scan(tmp_path / "s.h5", Scan(data=data + background, geometry=g, background=background,
                                       bubble_contrast=-0.1))
    part = read_scan(tmp_path / "s.h5", rows=(5, 17))
    assert part.geometry.shape == (6, 12, 32)
    assert np.array_equal(part.data, (data + background)[:, 5:17])
    assert np.array_equal(part.background, background[:, 5:17])
    # the window's geometry holds the same rays: projecting onto it gives the same rows
    assert np.allclose(MeshProjector(part.geometry).forward([bubble]), data[:, 5:17], atol=1e-6)


def test_rows_of_raw_counts_use_the_same_rows_of_flats_and_darks(tmp_path):
    g = _parallel(rows=10, cols=8, n=3)
    rng = np.random.default_rng(2)
    flats = rng.uniform(900, 1100, (4, 10, 8))
    darks = rng.uniform(5, 15, (2, 10, 8))
    counts = rng.uniform(100, 800, g.shape)
    with h5py.File(tmp_path / "raw.h5", "w") as f:
        v = f.create_dataset("geometry/vectors", data=g.vectors)
        v.attrs["kind"], v.attrs["det_rows"], v.attrs["det_cols"] = g.kind, 10, 8
        f.attrs["bubble_contrast"] = -0.1
        f["exchange/data"], f["exchange/data_white"], f["exchange/data_dark"] = counts, flats, darks
    whole = read_scan(tmp_path / "raw.h5")
    part = read_scan(tmp_path / "raw.h5", rows=(3, 7))
    assert np.allclose(part.data, whole.data[:, 3:7])


@pytest.mark.parametrize("rows, match", [((5, 5), "do not lie within"), ((-1, 4), "do not lie within"),
                                         ((3, 40), "do not lie within"), ("ab", "rows must be")])
def test_bad_rows_are_refused(tmp_path, rows, match):
    g = _parallel(rows=8, cols=8, n=2)
    write_scan(tmp_path / "s.h5", Scan(data=np.zeros(g.shape, np.float32), geometry=g, bubble_contrast=-0.1))
    with pytest.raises(ValueError, match=match):
        read_scan(tmp_path / "s.h5", rows=rows)


def test_rows_need_a_3d_scan(tmp_path):
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 3, endpoint=False), pixel_size=0.1, cols=8)
    write_scan(tmp_path / "s.h5", Scan(data=np.zeros(g.shape, np.float32), geometry=g, bubble_contrast=-0.1))
    with pytest.raises(ValueError, match="needs a 3D scan"):
        read_scan(tmp_path / "s.h5", rows=(0, 1))


# -- geometry in a slab's own coordinates ----------------------------------------------------------
@pytest.mark.parametrize("cone", [False, True], ids=["parallel", "cone"])
def test_translated_geometry_sees_the_moved_scene(cone):
    angles = np.linspace(0, np.pi, 5, endpoint=False)
    if cone:
        g = ScanGeometry.cone(angles, source_origin=30.0, origin_detector=10.0, pixel_size=0.1, cols=24, rows=20)
    else:
        g = _parallel(rows=20, cols=24, n=5)
    origin = np.array([0.1, -0.2, 0.3])
    bubble = sphere_surface([0.2, 0.1, 0.4], 0.35, attenuation=-0.1)
    moved = bubble.with_vertices(bubble.vertices - origin)
    a = MeshProjector(g).forward([bubble])
    b = MeshProjector(g.translated(origin)).forward([moved])
    assert np.abs(a).max() > 0.01 and np.allclose(a, b, atol=1e-5)


def test_plan_slabs_partitions_the_rows_and_clips_the_halos():
    from bubsub.clients.pipeline.regions.slabs import plan_slabs

    plan = plan_slabs(100, 3, 10)
    assert [s.core for s in plan] == [(0, 33), (33, 67), (67, 100)]
    assert [s.read for s in plan] == [(0, 43), (23, 77), (57, 100)]
    assert plan[0].first and not plan[0].last and plan[-1].last
    with pytest.raises(ValueError, match="cannot split"):
        plan_slabs(4, 5, 1)
    with pytest.raises(ValueError, match="halo must be"):
        plan_slabs(10, 2, -1)


def test_auto_keeps_a_tomography_size_column_whole_and_spreads_it_over_workers():
    from bubsub.clients.pipeline.reconstruct import ReconstructionSettings
    from bubsub.clients.pipeline.regions.slabs import SLAB_PIXELS, WHOLE_SCAN_SLABS, slab_count

    settings = ReconstructionSettings()
    column = _parallel(rows=256, cols=768, n=40)  # 7.9 million pixels: the ~600-bubble column's detector
    assert column.n_angles * column.det_rows * column.det_cols <= WHOLE_SCAN_SLABS * SLAB_PIXELS
    assert slab_count(None, column, settings, halo=40) == (1, 0)
    assert slab_count(None, column, settings, halo=40, workers=1) == (1, 0)
    # a cluster of 2 or 3 workers gets a slab each; of more, as many as keep cores of two halos
    assert slab_count(None, column, settings, halo=40, workers=2) == (2, 40)
    assert slab_count(None, column, settings, halo=40, workers=3) == (3, 40)
    assert slab_count(None, column, settings, halo=40, workers=16) == (256 // 80, 40)
    assert slab_count(None, column, settings, 1, halo=40, workers=2) == (1, 0)  # --slabs 1 is honoured
    # four times taller: about one slab per SLAB_PIXELS read
    tall = _parallel(rows=1024, cols=768, n=40)
    n, halo = slab_count(None, tall, settings, halo=40)
    per_slab = tall.n_angles * (tall.det_rows / n + 2 * halo) * tall.det_cols
    assert n > 1 and halo == 40 and 0.7 * SLAB_PIXELS < per_slab < 1.4 * SLAB_PIXELS
    cone = ScanGeometry.cone(np.linspace(0, 2 * np.pi, 40, endpoint=False), source_origin=300.0,
                             origin_detector=10.0, pixel_size=0.1, cols=768, rows=1024)
    assert slab_count(None, cone, settings, halo=40, workers=4) == (1, 0)


def test_cone_beam_slabs_are_refused():
    from bubsub.clients.pipeline.regions.slabs import check_slab_geometry

    g = ScanGeometry.cone(np.linspace(0, 2 * np.pi, 4, endpoint=False), source_origin=30.0, origin_detector=10.0,
                          pixel_size=0.1, cols=8, rows=8)
    with pytest.raises(ValueError, match="parallel-beam"):
        check_slab_geometry(g)
    check_slab_geometry(_parallel())


# -- ownership and stitching -----------------------------------------------------------------------
def _result(index, core, read, centres, n_rows=40, radius=0.2):
    from bubsub.clients.pipeline.regions.slabs import Slab, SlabResult

    return SlabResult(Slab(index, core, read, n_rows), [sphere_surface(c, radius, -0.1) for c in centres], {})


def test_stitch_keeps_every_bubble_once():
    from bubsub.clients.pipeline.regions.slabs import stitch

    g = _parallel(rows=40, cols=32)  # rows 0..40 span z = -2..2 mm; the seam at row 20 is z = 0
    lower = _result(0, (0, 20), (0, 28), [(0, 0, -1.0),      # owned by the lower slab
                                          (0.5, 0, -0.02),   # on the seam: seen by both ...
                                          (-0.5, 0, 0.3)])   # in the lower halo, seen whole: owned above
    upper = _result(1, (20, 40), (12, 40), [(0.5, 0, 0.02),  # ... and owned by both: one is dropped
                                            (-0.5, 0, 0.31),
                                            (0, 0.5, 1.2),
                                            (0.6, 0.6, -0.25)])  # in the upper halo only: the lower slab missed it
    surfaces, summary = stitch([lower, upper], g)
    z = sorted(round(float(s.fine().centroid[2]), 2) for s in surfaces)
    assert len(surfaces) == 5 and z in ([-1.0, -0.25, -0.02, 0.31, 1.2], [-1.0, -0.25, 0.02, 0.31, 1.2])
    assert summary["duplicates_dropped"] == 1 and summary["claimed_from_halo"] == 1 and summary["seam_cut"] == 0


def test_stitch_counts_a_bubble_cut_by_a_seam():
    from bubsub.clients.pipeline.regions.slabs import stitch

    g = _parallel(rows=40, cols=32)
    lower = _result(0, (0, 20), (0, 22), [(0, 0, -0.1)], radius=0.4)  # reaches z = 0.3 but rows read end at 0.2
    upper = _result(1, (20, 40), (18, 40), [(0, 0, 1.0)])
    surfaces, summary = stitch([lower, upper], g)
    assert len(surfaces) == 2 and summary["seam_cut"] == 1


# -- end to end: a bubble across the seam, resume, Dask ---------------------------------------------
SEAM_TRUTH = ((0.25, 0.15, 0.02, 0.3), (-0.35, -0.25, 0.75, 0.28), (0.3, -0.3, -0.75, 0.28))


@pytest.fixture(scope="module")
def seam_scan(tmp_path_factory):
    """A column of three bubbles, the first across the middle row (the seam of two slabs)."""
    from bubsub.core.foam.containers import sphere_mesh

    g = _parallel(rows=40, cols=36, n=16, pixel=0.05)
    truth = [sphere_mesh(c[:3], c[3], -0.1, subdivisions=4) for c in SEAM_TRUTH]
    data = MeshProjector(g).forward(truth) + np.random.default_rng(3).normal(0, 0.002, g.shape)
    path = tmp_path_factory.mktemp("seam") / "scan.h5"
    write_scan(path, Scan(data=data.astype(np.float32), geometry=g, bubble_contrast=-0.1))
    return path


def _quick():
    from bubsub.clients.pipeline.reconstruct import ReconstructionSettings

    # preview voxels of one detector pixel (the default would oversample this small detector)
    return ReconstructionSettings(iterations=25, progress=False, background_subtracted=True, refine=False,
                                  topology=False, voxel_size=0.05)


def _summary(surfaces):
    return sorted((tuple(np.round(s.fine().centroid, 2)), round(float(np.cbrt(3 * s.fine().volume / (4 * np.pi))), 3))
                  for s in surfaces)


def test_a_bubble_across_the_seam_comes_out_once_as_in_the_whole_scan(seam_scan, tmp_path):
    from bubsub.core.io.scanfile import read_scan
    from bubsub.core.metrics import bubble_mask, dice_dissimilarity
    from bubsub.clients.pipeline.reconstruct import reconstruct
    from bubsub.clients.pipeline.regions.slabs import reconstruct_slabs

    rec = reconstruct_slabs(seam_scan, _quick(), slabs=2, halo=10, out=tmp_path)
    assert rec.report["stitch"]["seam_cut"] == 0 and len(rec.report["slabs"]) == 2
    assert rec.report["preview"] == {"voxel_mm": pytest.approx(0.05), "finer_for_bubbles": False}
    assert [s["preview"]["voxel_mm"] for s in rec.report["slabs"]] == [pytest.approx(0.05)] * 2
    assert len(rec.surfaces) == 3
    for (c, r), truth in zip(_summary(rec.surfaces), sorted(SEAM_TRUTH, key=lambda t: t[:3])):
        assert np.linalg.norm(np.subtract(c, truth[:3])) < 0.03 and abs(r - truth[3]) < 0.02
    whole = reconstruct(read_scan(seam_scan), _quick()).surfaces
    shape, extent = (48, 48, 48), (-1.0, 1.0, -1.0, 1.0, -1.0, 1.0)
    a = bubble_mask([s.fine() for s in rec.surfaces], shape, extent)
    b = bubble_mask([s.fine() for s in whole], shape, extent)
    assert dice_dissimilarity(a, b) < 0.02
    assert sorted(p.name for p in (tmp_path / "slabs").iterdir()) == ["slab_000.npz", "slab_001.npz"]
    # the overlay's preview: the slabs' core slices stacked over the detector's height (40 rows of 0.05 mm)
    assert rec.preview.ndim == 3 and np.isclose(rec.preview_extent[4], -1.0, atol=0.06) \
        and np.isclose(rec.preview_extent[5], 1.0, atol=0.06)


def test_resume_reuses_finished_slabs_and_computes_the_rest(seam_scan, tmp_path, monkeypatch):
    from bubsub.clients.pipeline.regions import slabs

    real, calls = slabs.run_slab, []

    def interrupted_after_one(*args):
        if calls:
            raise KeyboardInterrupt
        calls.append(args[1].index)
        return real(*args)

    monkeypatch.setattr(slabs, "run_slab", interrupted_after_one)
    with pytest.raises(KeyboardInterrupt):
        slabs.reconstruct_slabs(seam_scan, _quick(), slabs=2, halo=10, out=tmp_path)
    assert [p.name for p in (tmp_path / "slabs").iterdir()] == ["slab_000.npz"]

    def only_the_second(*args):
        assert args[1].index == 1, "a finished slab was computed again"
        return real(*args)

    monkeypatch.setattr(slabs, "run_slab", only_the_second)
    rec = slabs.reconstruct_slabs(seam_scan, _quick(), slabs=2, halo=10, out=tmp_path, resume=True)
    assert rec.report["slabs_computed"] == 1 and len(rec.surfaces) == 3
    # other settings: the checkpoints do not match and every slab is computed again
    monkeypatch.setattr(slabs, "run_slab", real)
    again = slabs.reconstruct_slabs(seam_scan, __import__("dataclasses").replace(_quick(), iterations=20), slabs=2, halo=10,
                                    out=tmp_path, resume=True)
    assert again.report["slabs_computed"] == 2


def test_slabs_on_a_local_dask_cluster_match_the_in_process_run(seam_scan):
    pytest.importorskip("dask.distributed")
    from bubsub.clients.cluster.engine import local, open_client
    from bubsub.clients.pipeline.regions.slabs import reconstruct_slabs

    here = reconstruct_slabs(seam_scan, _quick(), slabs=2, halo=10)
    with open_client(local(2)) as client:
        there = reconstruct_slabs(seam_scan, _quick(), slabs=2, halo=10, client=client)
    for (c1, r1), (c2, r2) in zip(_summary(here.surfaces), _summary(there.surfaces)):
        assert np.allclose(c1, c2, atol=0.01) and abs(r1 - r2) < 0.005
    assert len(here.surfaces) == len(there.surfaces) == 3


def test_each_slab_is_a_fitting_job_on_the_projector_server(seam_scan):
    from service_support import ServerThread

    from bubsub.clients.pipeline.regions.slabs import reconstruct_slabs

    here = reconstruct_slabs(seam_scan, _quick(), slabs=2, halo=10)
    with ServerThread() as server:
        there = reconstruct_slabs(seam_scan, _quick(), slabs=2, halo=10, server=server.url)
        assert len(server.state.store) == 0  # every slab deleted its job
    assert len(there.surfaces) == 3
    for (c1, r1), (c2, r2) in zip(_summary(here.surfaces), _summary(there.surfaces)):
        assert np.allclose(c1, c2, atol=0.01) and abs(r1 - r2) < 0.005
