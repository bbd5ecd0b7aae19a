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
