"""4D subscans through slabs of detector rows: the row window of a scan in memory, cold and warm subscans slab by
slab against whole, track ids through the seam, the reconstruct4d flags and --resume."""

import json

import h5py
import numpy as np
import pytest

from bubsub.clients.cli import main
from bubsub.clients.pipeline.dynamic4d.chain import BubbleState, DynamicSettings, reconstruct_subscan
from bubsub.core import MeshProjector, ScanGeometry, sphere_surface
from bubsub.core.io.scanfile import Scan, read_scan, write_scan
from bubsub.core.io.subscans import subscan, subscan_layout

#: Bubbles ``(x, y, z, radius)`` of the later subscan (the earlier one: radii 0.9 x); the first lies across the
#: seam of two slabs (the middle row, z = 0).
TRUTH = ((0.25, 0.15, 0.02, 0.3), (-0.35, -0.25, 0.75, 0.28), (0.3, -0.3, -0.75, 0.28))
PER_SUBSCAN = 16


def _geometry(n_subscans, rows=40, cols=36):
    angles = np.tile(np.linspace(0, np.pi, PER_SUBSCAN, endpoint=False), n_subscans)
    return ScanGeometry.parallel(angles, pixel_size=0.05, cols=cols, rows=rows)


# -- the row window of a scan in memory --------------------------------------------------------------------
def test_row_window_in_memory_is_what_read_scan_reads_of_the_rows(tmp_path):
    g = _geometry(2, rows=24, cols=16)
    rng = np.random.default_rng(0)
    background = rng.uniform(0, 1, (PER_SUBSCAN, 24, 16)).astype(np.float32)  # one subscan's, repeated in the file
    scan = Scan(data=rng.uniform(0, 2, g.shape), geometry=g, bubble_contrast=-0.1, time=np.arange(g.n_angles) * 0.1,
                projections_per_subscan=PER_SUBSCAN)
    path = write_scan(tmp_path / "s.h5", scan)
    with h5py.File(path, "a") as f:
        f.create_dataset("exchange/background", data=background)
    rows = (5, 17)
    whole, part = read_scan(path), read_scan(path, rows=rows)
    # the whole scan's rows, and a subscan's (cut in memory from a scan read whole, or from the rows read)
    for cut, want in ((whole.row_window(rows), part), (_sub(whole, 1).row_window(rows), _sub(part, 1))):
        assert np.array_equal(cut.data, want.data) and np.array_equal(cut.background, want.background)
        assert np.array_equal(cut.geometry.vectors, want.geometry.vectors) and cut.geometry.shape == want.geometry.shape
        assert np.array_equal(cut.theta, want.theta) and np.array_equal(cut.time, want.time)
    assert whole.row_window(rows).path == part.path and whole.row_window(rows).projections_per_subscan == PER_SUBSCAN


@pytest.mark.parametrize("rows, match", [((5, 5), "the scan: rows .* do not lie within"), ((3, 40), "do not lie"),
                                         ("ab", "rows must be")])
def test_bad_row_windows_are_refused(rows, match):
    g = _geometry(1, rows=8, cols=8)
    with pytest.raises(ValueError, match=match):
        Scan(data=np.zeros(g.shape), geometry=g, bubble_contrast=-0.1).row_window(rows)
    flat = ScanGeometry.parallel(np.linspace(0, np.pi, 3, endpoint=False), pixel_size=0.1, cols=8)
    with pytest.raises(ValueError, match="needs a 3D scan"):
        Scan(data=np.zeros(flat.shape), geometry=flat, bubble_contrast=-0.1).row_window((0, 1))


# -- subscans slab by slab against whole ------------------------------------------------------------------
@pytest.fixture(scope="module")
def foam():
    """Two subscans of three bubbles that grow between them, static within each (no liquid background)."""
    from bubsub.core.foam.containers import sphere_mesh

    g = _geometry(2)
    data = np.empty(g.shape, np.float32)
    for k, scale in enumerate((0.9, 1.0)):
        part = slice(k * PER_SUBSCAN, (k + 1) * PER_SUBSCAN)
        data[part] = MeshProjector(g[part]).forward([sphere_mesh(c[:3], scale * c[3], -0.1, subdivisions=4)
                                                     for c in TRUTH])
    data += np.random.default_rng(3).normal(0, 0.002, g.shape).astype(np.float32)
    return Scan(data=data, geometry=g, bubble_contrast=-0.1, projections_per_subscan=PER_SUBSCAN)


def _settings(slabs, **kw):
    # preview voxels of one detector pixel (the default would oversample this small detector)
    return DynamicSettings(iterations=25, progress=False, topology=False, voxel_size=0.05, slabs=slabs, **kw)


def _sub(scan, k):
    return subscan(scan, subscan_layout(scan), k)


@pytest.fixture(scope="module")
def runs(foam):
    """``{slabs: (cold result of subscan 1, warm result of subscan 0)}``; both warm fits start from the whole
    scan's cold state, so that their bubbles compare track id by track id."""
    cold = {n: reconstruct_subscan(_sub(foam, 1), None, _settings(n), 1) for n in (1, 2)}
    return {n: (cold[n], reconstruct_subscan(_sub(foam, 0), cold[1].state, _settings(n), 0)) for n in (1, 2)}


def _bubbles(state):
    return {i: (np.asarray(s.fine().centroid), s.fine().volume) for i, s in zip(state.ids, state.surfaces())}


# Measured in two runs (25 iterations, pixel 0.05 mm), slabs against whole: cold starts' centroids within 0.0009 mm
# and volumes within 0.44 %, warm fits' within 0.0003 mm and 0.07 %. The bounds leave at least four times that.
CENTROID_MM, COLD_VOLUME, WARM_VOLUME = 0.005, 0.02, 0.005


def test_a_cold_subscan_in_slabs_matches_the_whole_one(runs):
    whole, slabbed = (_bubbles(runs[n][0].state) for n in (1, 2))
    assert sorted(whole) == sorted(slabbed) == [0, 1, 2]
    report = runs[2][0].report
    assert [s["core_rows"] for s in report["slabs"]] == [[0, 20], [20, 40]] and report["slab_halo_rows"] > 0
    assert report["stitch"]["owned"] == 3 and report["stitch"]["seam_cut"] == 0
    assert "slabs" not in runs[1][0].report
    for c, v in whole.values():  # the cold starts number their bubbles in their own order: matched by place
        c2, v2 = min(slabbed.values(), key=lambda b: np.linalg.norm(b[0] - c))
        assert np.linalg.norm(c2 - c) < CENTROID_MM and abs(v2 / v - 1) < COLD_VOLUME


def test_a_warm_subscan_in_slabs_keeps_every_track_id_once_and_matches_the_whole_one(runs):
    start = runs[1][0].state
    whole, slabbed = runs[1][1], runs[2][1]
    assert whole.state.ids == slabbed.state.ids == start.ids and slabbed.ended == ()
    for i, (c, v) in _bubbles(whole.state).items():
        c2, v2 = _bubbles(slabbed.state)[i]
        assert np.linalg.norm(c2 - c) < CENTROID_MM and abs(v2 / v - 1) < WARM_VOLUME
    report = slabbed.report
    seam = next(i for i, (c, _) in _bubbles(start).items() if abs(c[2]) < 0.1)
    # the bubble across the seam: fitted by both slabs, kept once, by the slab whose core holds its start
    assert [(s["bubbles"], s["bubbles_fitted"]) for s in report["slabs"]] == [(1, 2), (2, 2)]
    assert list(slabbed.state.ids).count(seam) == 1 and abs(_bubbles(slabbed.state)[seam][0][2] - 0.02) < 0.01
    assert report["stitch"] == {"owned": 3, "left_core": 0, "seam_cut": 0}
    for entry in report["slabs"]:
        assert {"read_rows", "seconds_total", "iterations", "stop_reason", "fit_levels"} <= set(entry)
    assert report["iterations"] == sum(s["iterations"] for s in report["slabs"])
    assert set(report["seconds_parts"]) == {"remesh", "fit", "detect"}  # the detection runs on the whole subscan


def test_a_bubble_whose_fit_crosses_the_seam_stays_with_the_slab_of_its_start(foam):
    # started below the seam (the lower slab's core), fitted to its place above it
    starts = [sphere_surface([0.25, 0.15, -0.06], 0.3, -0.1)] + [sphere_surface(c[:3], c[3], -0.1) for c in TRUTH[1:]]
    res = reconstruct_subscan(_sub(foam, 1), BubbleState.from_surfaces([4, 7, 9], starts), _settings(2), 1)
    assert res.state.ids == (4, 7, 9) and res.report["stitch"]["left_core"] == 1
    assert abs(_bubbles(res.state)[4][0][2] - 0.02) < 0.01


def test_slab_settings_that_cannot_be_honoured_are_refused():
    with pytest.raises(ValueError, match="holdout needs every subscan reconstructed whole"):
        DynamicSettings(holdout="odd", slabs=2)
    with pytest.raises(ValueError, match="slabs must be a positive integer"):
        DynamicSettings(slabs=0)
    cone = ScanGeometry.cone(np.linspace(0, 2 * np.pi, 4, endpoint=False), source_origin=30.0, origin_detector=10.0,
                             pixel_size=0.1, cols=8, rows=8)
    scan = Scan(data=np.zeros(cone.shape), geometry=cone, bubble_contrast=-0.1)
    with pytest.raises(ValueError, match="parallel-beam"):
        reconstruct_subscan(scan, None, _settings(2))


# -- the command ---------------------------------------------------------------------------------------------
def test_reconstruct4d_slab_flags_are_recorded_and_resume_refuses_others(foam, tmp_path, capsys, monkeypatch):
    import dataclasses

    from bubsub.clients.pipeline import reconstruct4d

    real, seen = reconstruct4d.reconstruct_subscan, []

    def quick(scan, previous, settings, index=0, time=0.0):
        # the command's settings as parsed, fitted with the quick preview of this small detector
        seen.append((settings.slabs, settings.slab_halo))
        static = dataclasses.replace(settings.static, topology=False, voxel_size=0.05)
        return real(scan, previous, dataclasses.replace(settings, static=static), index, time)

    monkeypatch.setattr(reconstruct4d, "reconstruct_subscan", quick)
    path = write_scan(tmp_path / "scan.h5", foam)
    out = tmp_path / "rec"
    run = ["reconstruct4d", str(path), "--out", str(out), "--iterations", "25", "--quiet"]
    assert main(run + ["--slabs", "2", "--slab-halo", "10"]) == 0
    assert seen == [(2, 10), (2, 10)]
    record = json.loads((out / "run.json").read_text())
    assert (record["slabs"], record["slab_halo"]) == (2, 10)
    per = json.loads((out / "report.json").read_text())["subscans"]
    assert [len(p["slabs"]) for p in per] == [2, 2] and {p["slab_halo_rows"] for p in per} == {10}
    capsys.readouterr()
    assert main(run + ["--slabs", "1", "--slab-halo", "10", "--resume"]) == 2
    assert "--resume: " in (err := capsys.readouterr().err) and "different ['slabs']" in err
    assert main(run + ["--slabs", "0"]) == 2 and "must be a positive integer" in capsys.readouterr().err
    assert len(seen) == 2  # refused before any subscan
