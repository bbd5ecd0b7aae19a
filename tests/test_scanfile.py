"""Scan files (Data Exchange HDF5) and atomic writing."""

import os

import h5py
import numpy as np
import pytest

from bubsub.core.io.atomic import atomic_open, atomic_path, atomic_write_bytes, atomic_write_text
from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.io.scanfile import MIN_TRANSMISSION, Scan, read_scan, theta_from_geometry, write_scan


def geom2d(n=5, cols=16):
    return ScanGeometry.parallel(np.linspace(0, np.pi, n, endpoint=False), pixel_size=0.1, cols=cols)


def geom3d(n=4, rows=6, cols=8):
    return ScanGeometry.cone(np.linspace(0, 2 * np.pi, n, endpoint=False), source_origin=50.0,
                             origin_detector=20.0, pixel_size=0.2, cols=cols, rows=rows)


def make_scan(geometry, background=True, seed=0):
    rng = np.random.default_rng(seed)
    data = rng.uniform(0, 2, geometry.shape).astype(np.float32)
    bg = rng.uniform(0, 2, geometry.shape).astype(np.float32) if background else None
    return Scan(data=data, geometry=geometry, background=bg, bubble_contrast=-0.1, attrs={"photons": 1e4})


def write_raw(path, geometry=None, **datasets):
    """Write a file with the given datasets (and a valid geometry unless geometry=False)."""
    g = geom2d() if geometry is None else geometry
    with h5py.File(path, "w") as f:
        if g is not False:
            v = f.create_dataset("geometry/vectors", data=g.vectors)
            v.attrs["kind"] = g.kind
            if g.ndim == 3:
                v.attrs["det_rows"], v.attrs["det_cols"] = g.det_rows, g.det_cols
            else:
                v.attrs["det_count"] = g.det_count
        f.attrs["bubble_contrast"] = -0.1
        for name, value in datasets.items():
            f.create_dataset(name.replace("__", "/"), data=value)
    return path


# -- round trips ------------------------------------------------------------------------------
@pytest.mark.parametrize("geometry", [geom2d(), geom3d()], ids=["2d", "3d"])
def test_round_trip(tmp_path, geometry):
    scan = make_scan(geometry)
    out = write_scan(tmp_path / "scan.h5", scan)
    assert out == tmp_path / "scan.h5" and scan.path == out
    back = read_scan(out)
    assert back.geometry == geometry
    assert np.array_equal(back.data, scan.data) and back.data.dtype == np.float32
    assert np.array_equal(back.background, scan.background)
    assert np.allclose(back.theta, scan.theta)
    assert back.bubble_contrast == -0.1
    assert back.attrs["photons"] == 1e4
    assert back.path == out
    assert np.allclose(back.bubble_data, scan.data - scan.background)
    with h5py.File(out, "r") as f:  # the Data Exchange layout itself
        assert f["exchange/data"].shape == geometry.shape
        assert f["geometry/vectors"].attrs["kind"] == geometry.kind
        assert f["exchange/theta"].attrs["units"] == "degrees"
    assert os.listdir(tmp_path) == ["scan.h5"]  # no temporary left behind


def test_round_trip_without_background_and_with_compression(tmp_path):
    scan = make_scan(geom3d(), background=False)
    back = read_scan(write_scan(tmp_path / "s.h5", scan, compression="gzip"))
    assert back.background is None
    assert np.array_equal(back.bubble_data, scan.data)


def test_theta_from_geometry_matches_the_angles():
    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    for g in (ScanGeometry.parallel(angles, cols=4), ScanGeometry.cone(angles, source_origin=10.0,
                                                                       origin_detector=5.0, cols=4, rows=2)):
        assert np.allclose(theta_from_geometry(g), np.degrees(angles))


def test_subset_keeps_everything_consistent():
    scan = make_scan(geom3d(n=6))
    even = scan.subset(slice(0, None, 2))
    assert even.n_angles == 3
    assert np.array_equal(even.data, scan.data[::2]) and np.array_equal(even.background, scan.background[::2])
    assert even.geometry == scan.geometry[::2]
    assert np.allclose(even.theta, scan.theta[::2])


# -- raw counts ----------------------------------------------------------------------------------
def test_raw_counts_are_flat_and_dark_corrected(tmp_path):
    g = geom3d()
    rng = np.random.default_rng(1)
    p = rng.uniform(0, 3, g.shape)
    dark = np.full(g.shape[1:], 100.0)
    white = rng.uniform(5000, 6000, g.shape[1:])
    counts = dark + (white - dark) * np.exp(-p)
    flats = np.stack([white - 50, white + 50])  # averages to white
    counts[0, 0, 0] = dark[0, 0] - 3  # noise below the dark level: clamped, not NaN
    path = write_raw(tmp_path / "raw.h5", g, exchange__data=counts, exchange__data_white=flats,
                     exchange__data_dark=dark[None])
    scan = read_scan(path)
    expected = p.copy()
    expected[0, 0, 0] = -np.log(MIN_TRANSMISSION)
    assert np.allclose(scan.data, expected, atol=1e-5)


def test_raw_counts_without_dark_field(tmp_path):
    g = geom2d()
    p = np.linspace(0, 2, np.prod(g.shape)).reshape(g.shape)
    path = write_raw(tmp_path / "raw.h5", g, exchange__data=np.round(1e4 * np.exp(-p)),
                     exchange__data_white=np.full(g.det_count, 1e4))
    assert np.allclose(read_scan(path).data, p, atol=1e-3)


def test_negative_raw_counts_are_rejected(tmp_path):
    g = geom2d()
    counts = np.full(g.shape, 10.0)
    counts[1, 2] = -1
    path = write_raw(tmp_path / "neg.h5", g, exchange__data=counts, exchange__data_white=np.full(g.det_count, 100.0))
    with pytest.raises(ValueError, match=r"'/exchange/data' .*1 negative"):
        read_scan(path)


def test_white_not_above_dark_is_rejected(tmp_path):
    g = geom2d()
    path = write_raw(tmp_path / "wd.h5", g, exchange__data=np.full(g.shape, 10.0),
                     exchange__data_white=np.full(g.det_count, 100.0), exchange__data_dark=np.full(g.det_count, 100.0))
    with pytest.raises(ValueError, match="data_white' must exceed '/exchange/data_dark"):
        read_scan(path)


def test_white_with_wrong_shape_is_rejected(tmp_path):
    g = geom2d()
    path = write_raw(tmp_path / "ws.h5", g, exchange__data=np.full(g.shape, 10.0),
                     exchange__data_white=np.full(g.det_count + 1, 100.0))
    with pytest.raises(ValueError, match="data_white' has shape"):
        read_scan(path)


# -- validation of files ---------------------------------------------------------------------------
def test_missing_data_is_named(tmp_path):
    with pytest.raises(ValueError, match="missing dataset '/exchange/data'"):
        read_scan(write_raw(tmp_path / "a.h5"))


def test_missing_geometry_is_named(tmp_path):
    path = write_raw(tmp_path / "a.h5", False, exchange__data=np.zeros(geom2d().shape))
    with pytest.raises(ValueError, match="missing dataset '/geometry/vectors'"):
        read_scan(path)


def test_wrong_kind_is_named(tmp_path):
    path = write_raw(tmp_path / "a.h5", exchange__data=np.zeros(geom2d().shape))
    with h5py.File(path, "a") as f:
        f["geometry/vectors"].attrs["kind"] = "parallel"
    with pytest.raises(ValueError, match="kind 'parallel'; expected one of"):
        read_scan(path)


def test_missing_detector_size_is_named(tmp_path):
    g = geom3d()
    path = write_raw(tmp_path / "a.h5", g, exchange__data=np.zeros(g.shape))
    with h5py.File(path, "a") as f:
        del f["geometry/vectors"].attrs["det_rows"]
    with pytest.raises(ValueError, match=r"missing attribute\(s\) \['det_rows'\]"):
        read_scan(path)


def test_data_shape_mismatch_names_both(tmp_path):
    g = geom3d()
    path = write_raw(tmp_path / "a.h5", g, exchange__data=np.zeros((g.n_angles, g.det_rows, g.det_cols + 1)))
    with pytest.raises(ValueError, match=r"'/exchange/data' has shape \(4, 6, 9\) but '/geometry/vectors' "
                                         r"describes \(n_angles, rows, cols\) = \(4, 6, 8\)"):
        read_scan(path)


def test_background_shape_mismatch_is_named(tmp_path):
    g = geom2d()
    path = write_raw(tmp_path / "a.h5", g, exchange__data=np.zeros(g.shape),
                     exchange__background=np.zeros((g.n_angles - 1, g.det_count)))
    with pytest.raises(ValueError, match="'/exchange/background' has shape"):
        read_scan(path)


def test_theta_length_mismatch_is_named(tmp_path):
    g = geom2d()
    path = write_raw(tmp_path / "a.h5", g, exchange__data=np.zeros(g.shape), exchange__theta=np.zeros(2))
    with pytest.raises(ValueError, match="'/exchange/theta' has shape"):
        read_scan(path)


@pytest.mark.parametrize("where", ["exchange__data", "exchange__background"])
def test_nan_and_inf_are_named(tmp_path, where):
    g = geom2d()
    bad = np.zeros(g.shape)
    bad[0, 0], bad[1, 1] = np.nan, np.inf
    sets = {"exchange__data": np.zeros(g.shape), where: bad}
    path = write_raw(tmp_path / "a.h5", g, **sets)
    with pytest.raises(ValueError, match=rf"'/{where.replace('__', '/')}' contains 2 non-finite values \(1 NaN, 1 inf\)"):
        read_scan(path)


def test_missing_contrast_is_named_and_can_be_supplied(tmp_path):
    g = geom2d()
    path = write_raw(tmp_path / "a.h5", g, exchange__data=np.zeros(g.shape))
    with h5py.File(path, "a") as f:
        del f.attrs["bubble_contrast"]
    with pytest.raises(ValueError, match="missing root attribute 'bubble_contrast'"):
        read_scan(path)
    assert read_scan(path, bubble_contrast=-0.05).bubble_contrast == -0.05


def test_not_hdf5_and_missing_file(tmp_path):
    junk = tmp_path / "junk.h5"
    junk.write_text("hello")
    with pytest.raises(ValueError, match="not a readable HDF5 file"):
        read_scan(junk)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_scan(tmp_path / "nope.h5")


# -- validation of Scan objects ----------------------------------------------------------------------
def test_scan_constructor_validates():
    g = geom2d()
    with pytest.raises(ValueError, match=r"data has shape \(5, 15\) but the geometry needs"):
        Scan(np.zeros((5, 15)), g, bubble_contrast=-0.1)
    with pytest.raises(ValueError, match="background has shape"):
        Scan(np.zeros(g.shape), g, background=np.zeros((4, 16)), bubble_contrast=-0.1)
    bad = np.zeros(g.shape)
    bad[2, 3] = np.nan
    with pytest.raises(ValueError, match="data contains 1 non-finite"):
        Scan(bad, g, bubble_contrast=-0.1)
    with pytest.raises(ValueError, match="bubble_contrast is required"):
        Scan(np.zeros(g.shape), g)
    with pytest.raises(ValueError, match="non-zero"):
        Scan(np.zeros(g.shape), g, bubble_contrast=0.0)
    with pytest.raises(ValueError, match="theta has shape"):
        Scan(np.zeros(g.shape), g, theta=np.zeros(3), bubble_contrast=-0.1)
    with pytest.raises(ValueError, match="reserved"):
        Scan(np.zeros(g.shape), g, bubble_contrast=-0.1, attrs={"bubble_contrast": 1})


# -- atomic writes -------------------------------------------------------------------------------------
def test_failed_scan_write_leaves_no_file_and_keeps_the_old_one(tmp_path, monkeypatch):
    dest = tmp_path / "scan.h5"
    old = make_scan(geom2d(), seed=1)
    write_scan(dest, old)
    before = dest.read_bytes()
    real = h5py.Group.create_dataset

    def failing(self, name, *args, **kwargs):
        if name == "background":
            raise RuntimeError("disk full")
        return real(self, name, *args, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", failing)
    with pytest.raises(RuntimeError, match="disk full"):
        write_scan(dest, make_scan(geom2d(), seed=2))
    assert dest.read_bytes() == before
    assert os.listdir(tmp_path) == ["scan.h5"]
    with pytest.raises(RuntimeError):
        write_scan(tmp_path / "new.h5", make_scan(geom2d(), seed=2))
    assert not (tmp_path / "new.h5").exists()
    assert os.listdir(tmp_path) == ["scan.h5"]


def test_atomic_path_success_and_failure(tmp_path):
    dest = tmp_path / "out.txt"
    with atomic_path(dest) as tmp:
        assert tmp.parent == tmp_path and tmp != dest
        tmp.write_text("one")
        assert not dest.exists()  # nothing under the final name before success
    assert dest.read_text() == "one"
    with pytest.raises(KeyError):
        with atomic_path(dest) as tmp:
            tmp.write_text("half")
            raise KeyError("boom")
    assert dest.read_text() == "one"
    assert os.listdir(tmp_path) == ["out.txt"]


def test_atomic_helpers(tmp_path):
    assert atomic_write_text(tmp_path / "a.txt", "héllo\n").read_text(encoding="utf-8") == "héllo\n"
    assert atomic_write_bytes(tmp_path / "b.bin", b"\x00\x01").read_bytes() == b"\x00\x01"
    with atomic_open(tmp_path / "c.txt") as fh:
        fh.write("x")
    assert (tmp_path / "c.txt").read_text() == "x"
    mask = os.umask(0)
    os.umask(mask)
    assert (tmp_path / "c.txt").stat().st_mode & 0o777 == 0o666 & ~mask  # not mkstemp's 0600
    with pytest.raises(FileExistsError):
        with atomic_open(tmp_path / "c.txt", "x"):
            pass
    with pytest.raises(ValueError, match="does not exist"):
        atomic_write_text(tmp_path / "missing" / "a.txt", "x")
    with pytest.raises(ValueError, match="is a directory"):
        atomic_write_text(tmp_path, "x")
    with pytest.raises(ValueError, match="mode"):
        with atomic_open(tmp_path / "d.txt", "r"):
            pass
    assert sorted(os.listdir(tmp_path)) == ["a.txt", "b.bin", "c.txt"]
