"""Scans of a foam wider than the detector (local tomography): the raw simulator's wider container against its
analytic projection, the axis found without air at the sides (or asked for), the liquid cylinder's chord profile
fitted from the data, ``bubsub prepare`` on such a raw scan, and the reconstruction's one-line note."""

import logging

import numpy as np
import pytest

from bubsub.core import MeshProjector
from bubsub.core.prep.background import chord_background, detector_offsets, radial_background, sees_air
from bubsub.core.prep.centre import center_seam, center_sharpest, center_sharpness, center_symmetry
from bubsub.core.prep.pipeline import SHARPEST_MARGIN, scan_geometry
from bubsub.core.projection.mesh import Polygon

C = -0.1
T = np.linspace(0, 2 * np.pi, 64, endpoint=False)


def _disc(centre, radius, attenuation):
    return Polygon(np.asarray(centre) + radius * np.stack([np.cos(T), np.sin(T)], 1) / np.cos(np.pi / 64),
                   attenuation)


def _foam(radius, n, seed, small=0.05, large=0.1):
    """Random disjoint gas discs (radii ``small..large`` mm) inside a disc of ``radius`` mm."""
    rng = np.random.default_rng(seed)
    discs = []
    for _ in range(20000):
        if len(discs) == n:
            break
        c, q = rng.uniform(-radius, radius, 2), rng.uniform(small, large)
        if np.hypot(*c) + q < radius and all(np.hypot(*(c - d)) > q + e + 0.01 for d, e in discs):
            discs.append((c, q))
    return discs


def _sinogram(axis_column, *, cols=96, pixel=0.02, angles=90, liquid_radius=1.5, n=40, seed=0):
    """Exact projections (180 degrees, ``angles`` views) of a liquid disc of ``liquid_radius`` times the field
    of view's radius filled with gas discs, the axis at ``axis_column``: ``(data, liquid, geometry, radius)``."""
    theta = np.linspace(0, 180, angles, endpoint=False)
    g = scan_geometry(theta, pixel_size=(pixel, pixel), cols=cols, axis_column=axis_column)
    fov = min(axis_column + 0.5, cols - 0.5 - axis_column) * pixel
    radius = liquid_radius * fov
    projector = MeshProjector(g, supersampling=2)
    liquid = projector.forward([_disc((0, 0), radius, 0.1)])
    gas = projector.forward([_disc(c, q, C) for c, q in _foam(radius, n, seed, 0.08 * fov, 0.16 * fov)])
    return liquid + gas, liquid, g, radius, theta


@pytest.mark.parametrize("axis", [47.5, 51.3])
def test_the_axis_is_found_without_air_at_the_sides(axis):
    data, _, _, _, theta = _sinogram(axis)
    assert not sees_air(data)
    assert center_seam(data, theta) == pytest.approx(axis, abs=0.25)
    assert center_symmetry(data) == pytest.approx(axis, abs=2.0)  # the bubbles' mean over 180 degrees is not
    with pytest.raises(ValueError, match="evenly spaced over 180 degrees"):
        center_seam(data[:-3], theta[:-3])


def test_the_liquid_cylinders_chord_profile_is_fitted_from_the_data():
    data, liquid, g, radius, _ = _sinogram(47.5, n=60)
    noisy = data + np.random.default_rng(1).normal(0, 0.003, data.shape)
    background, fit = chord_background(noisy.astype(np.float32), g)
    # the foam thins near the wall (no bubble crosses it), so the radius comes out a little large
    assert fit["radius_mm"] == pytest.approx(radius, rel=0.15)
    assert fit["liquid_attenuation"] == pytest.approx(0.1, rel=0.1)
    error = np.abs(background - liquid[0]).mean()
    assert error < 0.1 * liquid.max()
    # the ring profile of a reconstruction that sees only the interior (auto beside air) is further off
    radial = np.abs(radial_background(noisy.astype(np.float32), g) - liquid[0]).mean()
    assert error < 0.7 * radial
    s = detector_offsets(g)
    assert np.allclose(liquid[0], 0.2 * np.sqrt(np.maximum(radius ** 2 - s ** 2, 0)), atol=2e-3)  # the truth


def test_the_raw_simulators_wider_container_matches_its_analytic_projection():
    import bubsub.core.foam.raw as raw

    seen = {}
    detector = raw._detector

    def keep(intensity, theta, s, rng):
        seen["intensity"] = intensity
        return detector(intensity, theta, s, rng)

    s = raw.raw_settings(n_angles=2, cols=96, rows=2, pixel_size=0.01, axis_offset=3.3, distance=300.0,
                         container_radius=0.8, wall=0.0, supersample=2, wider_than_detector=True)
    with pytest.raises(ValueError, match="wider_than_detector=True"):
        raw.raw_settings(cols=96, pixel_size=0.01, container_radius=0.8, wall=0.0)
    phantom = raw.disc_foam(0, 0.8, n_bubbles=4, radius_range=(0.01, 0.02))
    try:
        raw._detector = keep
        raw.simulate_raw(phantom, s)
    finally:
        raw._detector = detector
    u = (np.arange(s.cols) - s.axis_column) * s.pixel_size
    liquid = s.liquid_mu * 2 * np.sqrt(s.container_radius ** 2 - u ** 2)
    far = np.ones(s.cols, bool)  # columns whose rays miss the four small bubbles
    for b in phantom.bubbles:
        c = b.vertices.mean(axis=0)
        for a in np.radians([0.0, 90.0]):  # the two views
            far &= np.abs(u - (c[0] * np.cos(a) + c[1] * np.sin(a))) > 0.05
    got = -np.log(seen["intensity"][0])
    assert np.abs(got - liquid)[far].max() < 0.01 * liquid.max()  # the edges too: no cut-off wave there


@pytest.mark.parametrize("axis, start", [(47.5, 49.0), (51.3, 49.8), (51.3, 52.8)])
def test_the_axis_is_refined_by_the_sharpest_fbp_of_the_row_continued_by_its_edges(axis, start):
    # a seam 1.5 pixels off: the least total variation of the FBP finds the axis once the truncated row is continued
    # by its edge columns; without the continuation the detector's edges, seen as the sample's, pull it away
    data, _, _, _, theta = _sinogram(axis, cols=128, pixel=0.015, angles=60)
    assert center_sharpness(data, theta, start, width=3.0, truncated=True) == pytest.approx(axis, abs=0.4)
    assert abs(center_sharpness(data, theta, start, width=3.0) - axis) > 1.0


@pytest.mark.parametrize("seed", [9, 18])
def test_prepare_finds_the_axis_of_a_raw_scan_wider_than_the_detector(seed, tmp_path):
    from bubsub.bench.fov_local import local_axis_case

    # the raw local-tomography scans of `python -m bubsub.bench fov --local-axis` whose seam alone lands 1.5 raw
    # pixels off; the simulator knows the true axis
    r = local_axis_case(tmp_path, seed)
    assert "refined by the least total variation" in r["method"]
    assert abs(r["error_px"]) < 0.5


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    """A raw local-tomography scan (flats, darks, 16 keV, 300 mm, axis 5.3 px off centre, a liquid cylinder 1.5
    times the field of view's radius filled with bubbles) prepared with --bin 2 --delta-beta 1450 --background
    auto and its axis given (the automatic search is tested below)."""
    from bubsub.core.foam.raw import disc_foam, raw_settings, write_raw_simulation
    from bubsub.core.prep import prepare, prepare_options

    out = tmp_path_factory.mktemp("local")
    cols, px, off = 160, 0.008, 5.3
    half = (cols / 2 - off) * px
    radius = 1.5 * half
    s = raw_settings(seed=2, n_angles=60, cols=cols, rows=2, pixel_size=px, axis_offset=off, distance=300.0,
                     container_radius=radius, wall=0.0, supersample=2, wider_than_detector=True)
    write_raw_simulation(out, disc_foam(2, radius, n_bubbles=40, radius_range=(0.1 * half, 0.2 * half)), s)
    report = prepare(out / "raw.h5", out / "scan.h5",
                     prepare_options(roi="1:2,:", bin=2, delta_beta=1450, center=s.axis_column, background="auto"),
                     progress=False)
    return out, {st["step"]: st for st in report["steps"]}, s, radius


def test_prepare_finds_the_liquid_of_a_sample_wider_than_the_detector(prepared):
    from bubsub.core.io.scanfile import read_scan

    out, steps, s, radius = prepared
    assert steps["phase_margin"]["cols_each_side"] > 0
    # no air at the sides, phase retrieval: the pixel gains the flats do not show divided out (--double-flat auto)
    assert 0 < steps["double_flat_field"]["log_gain_rms"] < steps["double_flat_field"]["log_gain_largest"] < 0.5
    fit = steps["background"]["wider_than_detector"]
    assert fit["radius_mm"] == pytest.approx(radius, rel=0.08)
    scan = read_scan(out / "scan.h5")
    s_mm = detector_offsets(scan.geometry)
    truth = s.liquid_mu * 2 * np.sqrt(radius ** 2 - s_mm ** 2)
    assert np.abs(scan.background[0] - truth).mean() < 0.15 * truth.max()
    assert steps["contrast"]["bubble_contrast_per_mm"] < 0


def test_a_prepared_local_scan_is_named_local_tomography_in_one_line(prepared, caplog):
    from bubsub.core.io.scanfile import read_scan
    from bubsub.clients.pipeline.inputs.sides import check_lateral_truncation

    scan = read_scan(prepared[0] / "scan.h5")
    with caplog.at_level(logging.WARNING, logger="bubsub"):
        text = check_lateral_truncation(scan)
    assert text.startswith("note: scan.h5 is local tomography") and [r.getMessage() for r in caplog.records] == [text]


def test_prepare_finds_the_axis_where_the_mean_projection_is_asymmetric(prepared, tmp_path):
    from bubsub.core.prep import prepare, prepare_options

    # this foam's few large bubbles make its mean over 180 degrees asymmetric (the symmetry search stands pixels
    # off); the sharpest FBP over the detector's middle confirms the seam
    report = prepare(prepared[0] / "raw.h5", tmp_path / "auto.h5",
                     prepare_options(roi="1:2,:", bin=2, delta_beta=1450, center="auto"), progress=False)
    step = next(x for x in report["steps"] if x["step"] == "center")
    assert step["method"].startswith("sharpest FBP over the detector's middle") and "checked by the seam" in step["method"]
    assert step["axis_column_raw"] == pytest.approx(prepared[2].axis_column, abs=0.5)


def test_prepare_takes_the_sharpest_fbp_where_the_seam_locks_elsewhere(tmp_path):
    from bubsub.bench.fov_local import local_axis_case

    # seed 36 of `python -m bubsub.bench fov --local-axis`: the seam's least lands 43 raw pixels off, its cost
    # has a local least at the sharpest FBP's column too
    r = local_axis_case(tmp_path, 36)
    assert "checked by a local least of the seam's cost" in r["method"]
    assert abs(r["error_px"]) < 0.5


@pytest.mark.parametrize("axis", [47.5, 51.3])
def test_the_sharpest_fbp_over_the_detectors_middle_finds_the_axis_and_says_how_distinct(axis):
    data, liquid, _, _, theta = _sinogram(axis, cols=128, pixel=0.015, angles=60)
    column, margin = center_sharpest(data, theta, truncated=True)
    assert column == pytest.approx(axis, abs=0.3) and margin > SHARPEST_MARGIN
    # a row of noise sharpens nowhere: its least lies at the search's edge
    noise = liquid + np.random.default_rng(0).normal(0, 0.01, data.shape)
    assert center_sharpest(noise, theta, truncated=True)[1] == 0.0


def test_prepare_asks_for_the_axis_of_a_row_with_nothing_to_sharpen(tmp_path):
    from bubsub.core.foam.raw import disc_foam, raw_settings, write_raw_simulation
    from bubsub.core.prep import prepare, prepare_options

    # the liquid cylinder and one bubble a fifth of a pixel across, wider than the detector: no feature sharpens
    # at one column more than at others
    cols, px, off = 160, 0.008, 5.3
    radius = 1.5 * (cols / 2 - off) * px
    s = raw_settings(seed=3, n_angles=60, cols=cols, rows=2, pixel_size=px, axis_offset=off, distance=300.0,
                     container_radius=radius, wall=0.0, supersample=2, wider_than_detector=True)
    write_raw_simulation(tmp_path, disc_foam(3, radius, n_bubbles=1, radius_range=(0.0015, 0.0016)), s)
    with pytest.raises(ValueError, match=r"^the rotation axis of this sample, wider than the detector \(no air at "
                                         r"its sides\), could not be found reliably: .* give the axis with --center"):
        prepare(tmp_path / "raw.h5", tmp_path / "auto.h5",
                prepare_options(roi="1:2,:", bin=2, delta_beta=1450, center="auto"), progress=False)
    assert not (tmp_path / "auto.h5").exists()


def test_prepare_takes_the_sharpest_fbp_with_a_warning_where_there_is_no_seam(prepared, tmp_path):
    from bubsub.core.prep import prepare, prepare_options

    # 57 of the 60 projections: not an even 180-degree scan, so no seam search checks the sharpest FBP
    with pytest.warns(UserWarning, match=r"taken at detector column .* unchecked: not an even 180-degree scan"):
        report = prepare(prepared[0] / "raw.h5", tmp_path / "auto.h5",
                         prepare_options(roi="1:2,:", bin=2, delta_beta=1450, center="auto", projections="0:57"),
                         progress=False)
    step = next(x for x in report["steps"] if x["step"] == "center")
    assert step["method"].startswith("sharpest FBP over the detector's middle")
    assert step["axis_column_raw"] == pytest.approx(prepared[2].axis_column, abs=0.5)


def test_a_coarsened_foam_wider_than_the_detector_reconstructs_through_prepare_and_reconstruct(tmp_path):
    # bench fov --local --local-foam large, seed 100: a few bubbles of 0.15-0.25 field-of-view radii; the fitted
    # liquid radius comes out 40 % large, and with the liquid alone as background the preview saw a liquid at 0.4 of
    # the contrast and the reconstruction a handful of bubbles for the whole field of view
    from bubsub.bench.fov_local import local_case

    scores = local_case(tmp_path / "beyond", 100, foam="large")
    assert abs(scores["axis_error_px"]) < 1.0
    assert scores["found"] == scores["truth"] >= 1 and scores["spurious"] == 0
    assert scores["ddi"] < 0.06  # 0.015
    alone = local_case(tmp_path / "alone", 100, foam="large", reach=np.inf)
    assert alone["ddi"] > 0.1  # 0.24
