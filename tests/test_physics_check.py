"""Scans no foam can give are refused before any work: the bubble signal against the liquid and the contrast.

The truth is the construction: each impossible scan is a simulated foam (voxel-projected, not the fitted mesh
model) altered so that it breaks a physical bound by a known margin: line integrals below zero, a bubble
signal larger than the liquid it replaces, gas paths longer than the field of view, one value everywhere.
"""

import shutil
import time

import h5py
import numpy as np
import pytest

from bubsub.clients.cli import main
from bubsub.clients.pipeline.inputs.checks import check_bubble_signal
from bubsub.clients.pipeline.inputs.physics import check_physical_signal, liquid_attenuation, longest_path
from bubsub.core import ScanGeometry
from bubsub.core.io.scanfile import read_scan


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "sim"
    assert main(["simulate", "--phantom", "foam2d", "--det-count", "400", "--angles", "12", "--seed", "3",
                 "--out", str(out)]) == 0
    return out


def _altered(sim, path, data=None, contrast=None, background=True):
    """A copy of the simulation's scan (written with h5py) with ``data(d, bg)`` as its data and, when
    ``background`` is callable, ``background(bg)`` as its background (False: none)."""
    shutil.copy(sim / "scan.h5", path)
    with h5py.File(path, "a") as f:
        d, bg = f["exchange/data"][...], f["exchange/background"][...]
        if data is not None:
            f["exchange/data"][...] = data(d, bg).astype(np.float32)
        if contrast is not None:
            f.attrs["bubble_contrast"] = contrast
        if background is False:
            del f["exchange/background"]
        elif callable(background):
            f["exchange/background"][...] = background(bg).astype(np.float32)
    return path


def test_a_sign_flipped_scan_is_refused_in_one_line_and_leaves_no_folder(sim, tmp_path, capsys):
    scan = _altered(sim, tmp_path / "flipped.h5", data=lambda d, bg: -np.abs(d) - 1)
    t0 = time.perf_counter()
    assert main(["reconstruct", str(scan), "--out", str(tmp_path / "rec"), "--quiet"]) == 2
    assert time.perf_counter() - t0 < 3  # before the voxel preview
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "100 % of the line integrals in /exchange/data are negative" in err
    assert not (tmp_path / "rec").exists()


@pytest.mark.parametrize("kind, data, contrast, background, words", [
    # bubbles 3x deeper than they are: on the big bubbles' rays more gas than liquid
    ("3x signal", lambda d, bg: bg + 3 * (d - bg), None, True, "line integrals in /exchange/data are negative"),
    # the contrast 50x too small: gas paths of up to 50x the foam's width
    ("tiny contrast", None, -0.002, True, "longer than the"),
    # the bubbles' signal alone, 20x too strong, so no background to compare with
    ("20x signal, no background", lambda d, bg: 20 * (d - bg), None, False, "gas paths up to"),
    # gas minus liquid larger than the liquid's own attenuation (0.1 1/mm): a contrast in 1/m, or 10x
    ("contrast in 1/m", None, -100.0, True, "larger in magnitude than the liquid's attenuation"),
    ("contrast 10x", None, -1.0, True, "larger in magnitude than the liquid's attenuation"),
    # transmissions written as line integrals: 1 in air, where nothing attenuates
    ("transmission", lambda d, bg: np.exp(-d), None, True, "on 100 % of the rays that miss the liquid"),
    ("one value", lambda d, bg: np.full_like(d, 0.5), None, True, "are all 0.5"),
    ("zeros", lambda d, bg: np.zeros_like(d), None, True, "are all 0"),
    # the background's sign flipped, data with it: data - background is still the bubbles' signal
    ("negative background", lambda d, bg: d - 2 * bg, None, lambda bg: -bg, "of /exchange/background is negative"),
])
def test_impossible_scans_are_refused(sim, tmp_path, kind, data, contrast, background, words):
    path = _altered(sim, tmp_path / "bad.h5", data=data, contrast=contrast, background=background)
    with pytest.raises(ValueError, match=words) as exc:
        check_bubble_signal(read_scan(path))
    assert "\n" not in str(exc.value)


def test_real_foams_pass(sim, tmp_path):
    scan = read_scan(sim / "scan.h5")
    check_physical_signal(scan)
    # the bubbles' projection alone (no background) is a possible scan too
    scan.data, scan.background = scan.bubble_data, None
    check_physical_signal(scan)
    # noisier: 300 photons
    noisy = tmp_path / "noisy"
    assert main(["simulate", "--phantom", "foam2d", "--det-count", "400", "--angles", "12", "--seed", "4",
                 "--photons", "300", "--out", str(noisy)]) == 0
    check_physical_signal(read_scan(noisy / "scan.h5"))


def test_the_liquids_attenuation_is_read_from_its_projection(sim):
    # foam2d: a 10 mm square of liquid of 0.1 1/mm (phantom.json), widest along its diagonal
    import json

    meta = json.loads((sim / "phantom.json").read_text())
    scan = read_scan(sim / "scan.h5")
    mu, width, top = liquid_attenuation(scan.background, scan.geometry, 0.01)
    assert mu == pytest.approx(meta["liquid_attenuation"], rel=0.05)
    assert width == pytest.approx(np.hypot(*meta["size"]), rel=0.05)


def test_the_longest_path_is_the_modelled_cylinder_crossed_by_the_steepest_ray():
    pix, cols, rows, so, od = 0.05, 200, 120, 40.0, 20.0
    # parallel: the diameter of 1.25 x the reconstructable disc, cols x pix wide
    g2 = ScanGeometry.parallel(np.linspace(0, np.pi, 9, endpoint=False), pixel_size=pix, cols=cols)
    assert longest_path(g2) == pytest.approx(1.25 * cols * pix)
    # cone: the disc shrinks by the magnification; the middle of the top row's ray is tilted by
    # atan(z / (so + od)), z that row's centre above the axis
    g3 = ScanGeometry.cone(np.linspace(0, 2 * np.pi, 9, endpoint=False), source_origin=so, origin_detector=od,
                           pixel_size=pix, cols=cols, rows=rows)
    r = 0.5 * cols * pix * so / (so + od)
    z = (0.5 * rows - 0.5) * pix
    # the middle of the row is between two pixel centres: the steepest pixel ray is half a pixel aside
    x = 0.5 * pix
    tilt = np.hypot(so + od, np.hypot(x, z)) / np.hypot(so + od, x)
    assert longest_path(g3) == pytest.approx(2 * 1.25 * r * tilt, rel=1e-9)


def test_reconstruct4d_refuses_a_sign_flipped_dynamic_scan_before_making_its_folder(tmp_path, capsys):
    sim = tmp_path / "sim4"
    assert main(["simulate", "--phantom", "expanding2d", "--subscans", "2", "--projections-per-subscan", "8",
                 "--det-count", "200", "--bubbles", "4", "--seed", "1", "--out", str(sim)]) == 0
    scan = _altered(sim, tmp_path / "flipped4d.h5", data=lambda d, bg: -np.abs(d) - 1)
    assert main(["reconstruct4d", str(scan), "--out", str(tmp_path / "rec4"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "flipped4d.h5: 100 % of the line integrals" in err
    assert not (tmp_path / "rec4").exists()


def test_a_dense_foam_wider_than_the_detector_is_not_refused_for_its_long_gas_paths(sim, tmp_path):
    # local tomography: a liquid disc 1.6 times the field of view's radius, 90 % gas, no air at the sides; its
    # central rays cross 2.9 field-of-view radii of gas, more than the 2.5 the modelled region holds, and the
    # scan is still possible (the gas beyond the model is what the field-of-view model absorbs)
    geometry = read_scan(sim / "scan.h5").geometry
    half = longest_path(geometry) / 2.5
    def chord(d):
        x = (np.arange(d.shape[-1]) - d.shape[-1] / 2 + 0.5) * (2 * half / d.shape[-1])
        return 2 * np.sqrt((1.6 * half) ** 2 - x ** 2)
    def texture(d):
        a = np.arange(d.shape[0])[:, None] * 0.7 + np.arange(d.shape[-1])[None, :] * 0.31
        return 0.9 + 0.05 * np.sin(a)
    path = _altered(sim, tmp_path / "wide.h5", contrast=-0.1,
                    data=lambda d, bg: 0.2 * chord(d) - 0.1 * chord(d) * texture(d),
                    background=lambda bg: 0.2 * chord(bg) + 0 * bg)
    scan = read_scan(path)
    assert float(np.max(-scan.bubble_data)) / 0.1 > 1.1 * longest_path(geometry)  # paths beyond the bound
    check_physical_signal(scan)  # no error
    # the same gas on a detector the foam does not fill (air at its sides) is refused
    narrow = _altered(sim, tmp_path / "narrow.h5", contrast=-0.1,
                      data=lambda d, bg: np.where(chord(d) > 1.6 * half * 1.9, 0.2 * chord(d) - 0.1 * chord(d)
                                                  * texture(d), 0.2 * chord(d)),
                      background=lambda bg: 0.2 * chord(bg) + 0 * bg)
    with pytest.raises(ValueError, match="gas paths"):
        check_physical_signal(read_scan(narrow))


def test_a_flipped_scan_reconstructed_in_slabs_is_refused_before_its_folder(tmp_path, capsys):
    sim = tmp_path / "col"
    assert main(["simulate", "--phantom", "column", "--bubbles", "40", "--det-count", "96", "--angles", "8",
                 "--seed", "1", "--out", str(sim)]) == 0
    scan = _altered(sim, tmp_path / "flipped.h5", data=lambda d, bg: -np.abs(d) - 1)
    capsys.readouterr()
    t0 = time.perf_counter()
    assert main(["reconstruct", str(scan), "--out", str(tmp_path / "rec"), "--slabs", "2", "--quiet"]) == 2
    assert time.perf_counter() - t0 < 20  # before the preview that sets the slabs' halo (a minute here)
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "are negative" in err
    assert not (tmp_path / "rec").exists()
