"""``bubsub prepare`` on small raw files: the output reads back, bad input is refused early and clearly,
an interrupted run leaves nothing, slabs do not change the result."""

import json

import h5py
import numpy as np
import pytest

from bubsub.clients.cli.main import main
from bubsub.core.io.scanfile import read_scan
from bubsub.core.prep import pipeline as prepare_module
from bubsub.core.prep.options import prepare_options
from bubsub.core.prep.pipeline import prepare

N, ROWS, COLS, AXIS = 60, 6, 96, 49.25
PIXEL_UM = 50.0


def _sinogram(theta_deg, rows=ROWS, cols=COLS, axis=AXIS):
    """Line integrals of a water cylinder (radius 1.8 mm) with two gas bubbles, axis at column ``axis``."""
    px = PIXEL_UM * 1e-3
    s = (np.arange(cols) - axis) * px
    th = np.radians(theta_deg)[:, None]
    chord = lambda r, c: 2 * np.sqrt(np.maximum(r * r - (s[None] - c) ** 2, 0))
    p = 0.1 * chord(1.8, 0.0) * np.ones_like(th)
    for bx, by, r in [(0.6, 0.3, 0.4), (-0.7, -0.5, 0.3)]:
        p = p - 0.1 * chord(r, bx * np.cos(th) + by * np.sin(th))
    return np.repeat(p[:, None, :], rows, axis=1)


def make_raw(path, *, theta=None, flats=True, darks=True, flat_shape=None, dark_shape=None, theta_units=None,
             pixel_units="um", n=N, seed=0):
    rng = np.random.default_rng(seed)
    theta = np.linspace(0, 180, n, endpoint=False) if theta is None else np.asarray(theta, float)
    i0 = 5000.0
    counts = rng.poisson(i0 * np.exp(-_sinogram(theta if theta_units != "rad" else np.degrees(theta)))) + 100
    with h5py.File(path, "w") as f:
        f["exchange/data"] = counts.astype(np.uint16)
        shape = flat_shape or (ROWS, COLS)
        if flats:
            f["exchange/data_white"] = (rng.poisson(i0, (6, *shape)) + 100).astype(np.uint16)
        if darks:
            f["exchange/data_dark"] = np.full((4, *(dark_shape or shape)), 100, np.uint16)
        t = f.create_dataset("exchange/theta", data=theta)
        if theta_units:
            t.attrs["units"] = theta_units
        px = f.create_dataset("measurement/instrument/detector/pixel_size_x", data=PIXEL_UM)
        px.attrs["units"] = pixel_units
        f["measurement/instrument/monochromator/energy"] = 16.0
        f["measurement/instrument/detection_system/distance"] = 250.0
    return path


@pytest.fixture
def raw(tmp_path):
    return make_raw(tmp_path / "raw.h5")


def run(argv, capsys):
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse refuses a bad option value
        code = exc.code
    captured = capsys.readouterr()
    return code, captured.out + captured.err


def test_prepare_writes_a_scan_that_reconstruct_reads(raw, tmp_path, capsys):
    out = tmp_path / "scan.h5"
    code, text = run(["prepare", str(raw), "--out", str(out), "--quiet"], capsys)
    assert code == 0, text
    scan = read_scan(out)
    assert scan.ndim == 3 and scan.n_angles == N
    steps = {s["step"]: s for s in json.loads((tmp_path / "scan.h5.report.json").read_text())["steps"]}
    assert steps["center"]["axis_column_raw"] == pytest.approx(AXIS, abs=0.3)
    # the geometry puts the axis at the origin: the pixel whose centre is nearest to it
    g = scan.geometry
    u = g.vectors[0, 6:9]
    d = g.vectors[0, 3:6]
    axis_out = g.det_cols / 2 - 0.5 - np.dot(d, u) / np.dot(u, u)
    crop0 = steps["crop_to_axis"]["cols"][0]
    assert axis_out + crop0 == pytest.approx(AXIS, abs=0.3)
    # line integrals and background agree with the analytic object
    truth = _sinogram(scan.theta, cols=g.det_cols, axis=axis_out)
    assert np.abs(scan.data - truth).mean() < 0.02
    assert scan.bubble_contrast == pytest.approx(-0.1, abs=0.03)
    assert scan.background is not None
    assert np.median(np.abs(scan.bubble_data - (truth - _cylinder(g.det_cols, axis_out)))) < 0.02


def _cylinder(cols, axis):
    s = (np.arange(cols) - axis) * PIXEL_UM * 1e-3
    return 0.1 * 2 * np.sqrt(np.maximum(1.8 ** 2 - s * s, 0))[None, None, :]


def test_slab_size_does_not_change_the_result(raw, tmp_path):
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    prepare(raw, a, prepare_options(slab_mb=0.01, center=AXIS), progress=False)
    prepare(raw, b, prepare_options(center=AXIS), progress=False)
    ra, rb = json.loads(a.with_name("a.h5.report.json").read_text()), json.loads(b.with_name("b.h5.report.json").read_text())
    assert ra["steps"][-3]["slab_projections"] < N <= rb["steps"][-3]["slab_projections"]
    sa, sb = read_scan(a), read_scan(b)
    assert np.array_equal(sa.data, sb.data) and np.array_equal(sa.background, sb.background)


def test_roi_bin_projections_and_2d_output(raw, tmp_path, capsys):
    out = tmp_path / "scan2d.h5"
    code, text = run(["prepare", str(raw), "--out", str(out), "--roi", "2:4,4:96", "--bin", "2",
                      "--projections", "0:60:2", "--center", str(AXIS), "--quiet"], capsys)
    assert code == 0, text
    scan = read_scan(out)
    assert scan.ndim == 2 and scan.n_angles == 30
    assert scan.theta[1] == pytest.approx(6.0)
    assert scan.geometry.vectors[0, 4] == pytest.approx(2 * PIXEL_UM * 1e-3)


@pytest.mark.parametrize("kwargs, args, message", [
    (dict(flats=False), [], "no flats .*--no-flat"),
    (dict(darks=False), [], "no darks .*--no-flat"),
    (dict(flat_shape=(ROWS, COLS - 2)), [], "data_white.* frames are .* but the projections are"),
    (dict(dark_shape=(ROWS - 1, COLS)), [], "data_dark.* frames are .* but the projections are"),
    (dict(theta=np.r_[np.linspace(0, 120, N // 2), np.linspace(60, 180, N // 2)]), [], "not monotonic"),  # steps back
    (dict(theta=np.r_[np.linspace(0, 90, 30), np.linspace(0, 90, 30)]), [], "not monotonic.*--projections"),
    (dict(theta=np.linspace(0, np.pi, N, endpoint=False)), [], "look like radians.*--theta-units rad"),
    (dict(pixel_units="furlong"), [], "unknown units 'furlong'"),
    (dict(theta_units="gradians"), [], "unknown units 'gradians'"),
    ({}, ["--roi", "0:4,0:200"], "outside the detector"),
    ({}, ["--bin", "5"], "--bin 5 does not divide"),
    ({}, ["--pixel-size", "3furlong"], "unknown unit"),
    ({}, ["--delta-beta", "1000", "--energy", "16parsec"], "unknown unit"),
    ({}, ["--roi", "4:2,:"], "roi rows range 4:2 is empty"),
    ({}, ["--delta-beta", "1000", "--energy", "16keV"], None),
    ({}, ["--background", "missing.h5"], "not a file"),
    ({}, ["--center", "500"], "outside the ROI"),
])
def test_bad_input_is_refused_with_a_clear_message(tmp_path, capsys, kwargs, args, message):
    raw = make_raw(tmp_path / "raw.h5", **kwargs)
    out = tmp_path / "scan.h5"
    code, text = run(["prepare", str(raw), "--out", str(out), "--quiet", *args], capsys)
    if message is None:  # a valid variant, for contrast with its neighbours
        assert code == 0, text
        return
    assert code == 2, text
    import re

    assert re.search(message, text), text
    assert not out.exists()
    assert not list(tmp_path.glob(".scan.h5*"))


def test_no_flat_proceeds_without_flats(tmp_path, capsys):
    raw = make_raw(tmp_path / "raw.h5", flats=False)
    out = tmp_path / "scan.h5"
    code, text = run(["prepare", str(raw), "--out", str(out), "--no-flat", "--quiet"], capsys)
    assert code == 0, text
    assert read_scan(out).bubble_contrast < 0


def test_theta_in_radians_when_told(tmp_path, capsys):
    raw = make_raw(tmp_path / "raw.h5", theta=np.linspace(0, np.pi, N, endpoint=False), theta_units="rad")
    out = tmp_path / "scan.h5"
    code, text = run(["prepare", str(raw), "--out", str(out), "--quiet"], capsys)
    assert code == 0, text
    assert read_scan(out).theta[-1] == pytest.approx(177.0)


def test_wrong_contrast_sign_is_refused(raw, tmp_path, capsys):
    out = tmp_path / "scan.h5"
    code, text = run(["prepare", str(raw), "--out", str(out), "--contrast", "0.1", "--quiet"], capsys)
    assert code == 2 and "wrong sign" in text
    assert not out.exists()


def test_interrupted_prepare_leaves_no_file(raw, tmp_path, monkeypatch, capsys):
    out = tmp_path / "scan.h5"
    out.write_bytes(b"an older scan")

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(prepare_module, "radial_background", interrupt)
    code, text = run(["prepare", str(raw), "--out", str(out), "--quiet"], capsys)
    assert code == 130 and "interrupted" in text
    assert out.read_bytes() == b"an older scan"  # the old file is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw.h5", "scan.h5"]  # no temporary left


def test_tiff_folder_gives_the_same_scan(raw, tmp_path):
    tifffile = pytest.importorskip("tifffile")
    folder = tmp_path / "tiffs"
    folder.mkdir()
    with h5py.File(raw) as f:
        for i, img in enumerate(f["exchange/data"][()]):
            tifffile.imwrite(folder / f"proj_{i:04d}.tif", img)
        tifffile.imwrite(folder / "flat_0000.tif", f["exchange/data_white"][()], photometric="minisblack")  # multi-page
        tifffile.imwrite(folder / "dark_0000.tif", f["exchange/data_dark"][()], photometric="minisblack")
        np.savetxt(folder / "angles.txt", f["exchange/theta"][()])
    opts = prepare_options(pixel_size=PIXEL_UM * 1e-3, center=AXIS)
    prepare(folder, tmp_path / "t.h5", opts, progress=False)
    prepare(raw, tmp_path / "h.h5", opts, progress=False)
    a, b = read_scan(tmp_path / "t.h5"), read_scan(tmp_path / "h.h5")
    assert np.array_equal(a.data, b.data) and a.geometry == b.geometry


def test_bubbles_at_the_edge_of_the_field_of_view_are_flagged():
    from bubsub.clients.pipeline.inputs.fov import field_of_view, truncated_flags
    from bubsub.core import circle_surface
    from bubsub.core.projection.geometry import ScanGeometry
    from bubsub.core.prep.pipeline import scan_geometry

    g = ScanGeometry.parallel(np.radians(np.arange(90) * 2.0), pixel_size=0.01, cols=400)
    assert field_of_view(g) == pytest.approx((2.0, 0.0))
    # an axis 10 pixels right of the detector centre leaves 1.9 mm on the short side
    shifted = scan_geometry(np.arange(90) * 2.0, pixel_size=(0.01, 0.01), cols=400, axis_column=209.5)
    assert field_of_view(shifted)[0] == pytest.approx(1.9)
    inside = circle_surface([0.5, 0.0], 0.5, -0.1, 9).fine()
    cut = circle_surface([1.7, 0.0], 0.5, -0.1, 9).fine()
    assert truncated_flags([inside, cut], field_of_view(shifted), 0.01) == [0, 1]


def test_sigterm_during_prepare_leaves_no_file(raw, tmp_path, monkeypatch, capsys):
    import os
    import signal

    out = tmp_path / "scan.h5"
    monkeypatch.setattr(prepare_module, "radial_background", lambda *a, **k: os.kill(os.getpid(), signal.SIGTERM))
    code, text = run(["prepare", str(raw), "--out", str(out), "--quiet"], capsys)
    assert code == 130 and "interrupted" in text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw.h5"]
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # restored


def test_redirected_prepare_prints_one_plain_line_per_pass(raw, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("BUBSUB_PROGRESS", raising=False)
    code, text = run(["prepare", str(raw), "--out", str(tmp_path / "scan.h5"), "--center", str(AXIS)], capsys)
    assert code == 0, text
    assert "\r" not in text  # no bar in a log file
    passes = [line for line in text.splitlines() if line.startswith("pass ")]
    assert len(passes) == 2 and passes[0].startswith(f"pass 1: flats, phase, -log: {N} projections, ")
    assert passes[1].startswith("pass 2: stripes, background: ") and " rows, " in passes[1]
