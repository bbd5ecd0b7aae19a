"""The preparation steps against independent truths: Paganin's analytic transfer function, a
Fresnel-propagated phase object, a known rotation axis, flats that drift in time, bad pixels."""

import numpy as np
import pytest

from bubsub.core.prep.centre import center_pair, center_sharpness, center_vo, closest_pair
from bubsub.core.prep.flats import FlatModel, find_bad_pixels, repair_pixels
from bubsub.core.prep.options import parse_quantity, parse_roi, prepare_options
from bubsub.core.prep.phase import fresnel_propagate, paganin_filter, paganin_transfer, wavelength_mm
from bubsub.core.prep.background import envelope_background


def test_wavelength_of_16_kev():
    assert wavelength_mm(16.0) == pytest.approx(0.7749e-7, rel=1e-3)  # 0.7749 Angstrom


@pytest.mark.parametrize("k", [3, 17, 40])
def test_paganin_filter_scales_a_cosine_by_the_analytic_transfer(k):
    rows, cols, px = 64, 256, 0.003
    x = np.arange(cols)
    img = 0.6 + 0.2 * np.cos(2 * np.pi * k * x / cols)[None, :].repeat(rows, 0)
    kw = dict(energy=16.0, distance=250.0, delta_beta=500.0)
    out = paganin_filter(img, pixel_size=px, pad=False, **kw)
    u = k / (cols * px)  # cycles per mm
    h = paganin_transfer(u * u, **kw)
    assert 0.01 < h < 0.99  # the frequencies tested are really filtered
    amp = 2 * np.abs(np.fft.rfft(out[rows // 2])[k]) / cols
    assert amp == pytest.approx(0.2 * h, rel=1e-4)
    assert out.mean() == pytest.approx(0.6, rel=1e-5)  # the mean passes unchanged


def test_paganin_tomopy_alpha_is_beta_over_delta():
    # TomoPy writes alpha / (lambda z w^2 / (4 pi) + alpha) with w = 2 pi u
    lam, z, alpha, u = wavelength_mm(20.0), 100.0, 1e-3, 50.0
    tomopy = alpha / (lam * z * (2 * np.pi * u) ** 2 / (4 * np.pi) + alpha)
    assert paganin_transfer(u * u, energy=20.0, distance=z, delta_beta=1 / alpha) == pytest.approx(tomopy, rel=1e-12)


def test_paganin_recovers_the_thickness_of_a_propagated_water_cylinder():
    """A water cylinder imaged at 16 keV and 250 mm: -log of the raw intensity rings at the edges,
    Paganin's filter gives back mu * t."""
    energy, z, mu, delta = 16.0, 250.0, 0.1, 9.0e-7
    beta = mu * wavelength_mm(energy) / (4 * np.pi)
    px, n = 0.001, 8192
    x = (np.arange(n) - n / 2 + 0.5) * px
    t = 2 * np.sqrt(np.maximum(0.8 ** 2 - x ** 2, 0))  # chord of a 0.8 mm cylinder, mm
    k = 2 * np.pi / wavelength_mm(energy)
    field = np.exp(-k * (beta + 1j * delta) * t)
    intensity = np.abs(fresnel_propagate(field, pixel_size=px, energy=energy, distance=z)) ** 2
    img = np.repeat(intensity[None], 4, axis=0)
    retrieved = -np.log(paganin_filter(img, pixel_size=px, energy=energy, distance=z, delta_beta=delta / beta)[2])
    naive = -np.log(intensity)
    inside = np.abs(x) < 0.7  # away from the tangent rays
    err_pag = np.abs(retrieved - mu * t)[inside].max() / (mu * t).max()
    err_naive = np.abs(naive - mu * t)[inside].max() / (mu * t).max()
    assert err_pag < 0.03
    assert err_naive > 5 * err_pag  # the phase contrast is really there


def test_center_pair_finds_a_known_axis():
    rng = np.random.default_rng(0)
    cols, axis = 300, 161.3
    x = np.arange(cols)
    obj = lambda pos: np.exp(-0.5 * ((pos - 20) / 6) ** 2) + 0.5 * np.exp(-0.5 * ((pos + 35) / 3) ** 2)
    p0 = obj(x - axis) + 0.01 * rng.normal(size=cols)
    p180 = obj(axis - x) + 0.01 * rng.normal(size=cols)
    assert center_pair(p0[None].repeat(4, 0), p180[None].repeat(4, 0)) == pytest.approx(axis, abs=0.1)


def test_center_vo_finds_a_known_axis():
    cols, axis, n = 256, 140.0, 180
    th = np.radians(np.arange(n))
    x = np.arange(cols) - axis
    sino = np.zeros((n, cols))
    for (px, py, r, a) in [(10.0, 5.0, 8.0, 1.0), (-30.0, 12.0, 5.0, 0.7), (0.0, -40.0, 10.0, 0.5)]:
        s = px * np.cos(th) + py * np.sin(th)
        sino += a * 2 * np.sqrt(np.maximum(r * r - (x[None] - s[:, None]) ** 2, 0))
    assert center_vo(sino) == pytest.approx(axis, abs=0.5)


@pytest.mark.parametrize("wide", [False, True])
@pytest.mark.parametrize("start", [-1.2, 0.9])
def test_center_sharpness_refines_an_axis_a_pixel_off(start, wide):
    # analytic chords of gas discs (0.1 deep per unit length) in a liquid disc within the detector, or in one
    # 1.5 times wider than it (no air at the sides); 60 projections over 180 degrees, the axis between columns
    cols, axis = 128, 66.3
    th = np.radians(np.arange(60) * 3.0)
    x = np.arange(cols) - axis
    liquid = 1.5 * cols / 2 if wide else 0.45 * cols
    sino = np.broadcast_to(0.1 * 2 * np.sqrt(np.maximum(liquid ** 2 - x ** 2, 0)), (th.size, cols)).copy()
    for (px, py, r) in [(10.0, 5.0, 8.0), (-30.0, 12.0, 5.0), (0.0, -40.0, 10.0), (25.0, -20.0, 6.0), (-8.0, 30.0, 7.0)]:
        s = px * np.cos(th) + py * np.sin(th)
        sino -= 0.1 * 2 * np.sqrt(np.maximum(r * r - (x[None] - s[:, None]) ** 2, 0))
    assert center_sharpness(sino, np.degrees(th), axis + start) == pytest.approx(axis, abs=0.15)


def test_closest_pair():
    i, j, err = closest_pair(np.arange(0, 181, 1.0))
    assert err == 0 and (j - i) == 180


def test_interpolated_flats_follow_a_decaying_beam_that_the_mean_does_not():
    rows, cols, n = 4, 50, 20
    pattern = 1 + 0.2 * np.sin(np.arange(cols) / 5)[None].repeat(rows, 0)
    beam = lambda t: 1000 * (1 - 0.01 * t) * pattern  # 20 % decay over the scan
    dark = np.full((rows, cols), 10.0, np.float32)
    before, after = beam(-0.5), beam(n - 0.5)
    true_t = 0.5
    counts = np.stack([beam(i) * true_t + dark for i in range(n)]).astype(np.float32)
    bad = np.zeros((rows, cols), bool)
    interp = FlatModel("interp", dark, np.stack([before + dark, after + dark]).astype(np.float32),
                       np.array([-0.5, n - 0.5]), bad)
    mean = FlatModel("mean", dark, ((before + after) / 2 + dark)[None].astype(np.float32), np.zeros(1), bad)
    t_interp, _ = interp.transmission(counts, np.arange(n))
    t_mean, _ = mean.transmission(counts, np.arange(n))
    assert np.abs(t_interp - true_t).max() < 1e-4
    assert np.abs(t_mean - true_t).max() > 0.04


def test_best_flat_picks_the_matching_pattern():
    rows, cols = 6, 80
    rng = np.random.default_rng(1)
    patterns = [1 + 0.3 * np.sin(np.arange(cols) / 4 + ph)[None].repeat(rows, 0) for ph in (0.0, 1.0, 2.0)]
    dark = np.zeros((rows, cols), np.float32)
    flats = np.stack([1000 * p for p in patterns]).astype(np.float32)
    air = np.zeros((rows, cols), bool)
    air[:, :15] = air[:, -15:] = True
    sample = np.ones((rows, cols))
    sample[:, 15:-15] = 0.4
    counts = np.stack([0.9 * 1000 * patterns[g] * sample for g in (2, 0, 1)]).astype(np.float32)
    model = FlatModel("best", dark, flats, np.arange(3.0), np.zeros((rows, cols), bool), air)
    t, chosen = model.transmission(counts + rng.normal(0, 0.5, counts.shape).astype(np.float32), np.arange(3))
    assert chosen == [2, 0, 1]
    assert np.abs(t - sample).max() < 0.01


def test_bad_pixels_are_found_and_repaired():
    rows, cols = 10, 12
    flat = np.full((rows, cols), 1000.0)
    dark = np.full((rows, cols), 100.0)
    flat[2, 3] = 0.0  # dead
    dark[5, 7] = 60000.0  # hot
    flat[7, 1] = 3000.0  # stuck bright
    bad = find_bad_pixels(flat, dark)
    assert set(zip(*np.nonzero(bad))) == {(2, 3), (5, 7), (7, 1)}
    img = np.full((1, rows, cols), 0.5, np.float32)
    img[0, bad] = 9.0
    repair_pixels(img, bad)
    assert np.allclose(img, 0.5)


def test_envelope_background_of_a_rotation_invariant_container():
    rng = np.random.default_rng(2)
    n, cols = 120, 200
    x = np.arange(cols) - 100.0
    bg = 0.1 * 2 * np.sqrt(np.maximum(80.0 ** 2 - x ** 2, 0)) * 0.05
    data = np.repeat(bg[None], n, 0)
    th = np.radians(np.arange(n) * 1.5)
    for px, py, r in [(20, 10, 8), (-30, -5, 6)]:  # bubbles lower the line integrals
        s = px * np.cos(th) + py * np.sin(th)
        data -= 0.1 * 0.05 * 2 * np.sqrt(np.maximum(r * r - (x[None] - s[:, None]) ** 2, 0))
    noisy = data + 0.005 * rng.normal(size=data.shape)
    est = envelope_background(noisy)
    assert np.abs(est - bg).max() < 0.01
    assert abs(np.mean(est - bg)) < 0.001  # not biased upward by the noise


def test_options_parse_and_reject():
    assert parse_roi("10:20,:300") == ((10, 20), (None, 300))
    assert parse_quantity("3um", "length", name="p") == pytest.approx(0.003)
    assert parse_quantity("25 cm", "length", name="d") == pytest.approx(250.0)
    assert parse_quantity("16", "energy", name="e") == 16.0
    with pytest.raises(ValueError, match="unknown unit"):
        parse_quantity("3 furlong", "length", name="--pixel-size")
    with pytest.raises(ValueError, match="empty"):
        parse_roi("20:10,:")
    with pytest.raises(ValueError, match="flat must be one of"):
        prepare_options(flat="median")
    with pytest.raises(ValueError, match="center"):
        prepare_options(center="left")
    assert repr(prepare_options(bin=2)) == "prepare_options(bin=2)"


@pytest.mark.parametrize("n, cols, px", [(180, 256, 0.04), (360, 512, 0.02)])  # the FBP: every 2nd / 3rd angle,
def test_radial_background_where_every_ray_crosses_a_bubble(n, cols, px):  # 256 pixels (all / half the columns)
    """Bubbles around the axis hide the container from every angle at the central columns: the
    envelope over angles is biased there, the ring profile of the reconstruction is not."""
    from bubsub.core.prep.background import radial_background
    from bubsub.core.projection.geometry import ScanGeometry

    th = np.radians(np.arange(n) * 180.0 / n)
    g = ScanGeometry.parallel(th, pixel_size=px, cols=cols)
    s = (np.arange(cols) - cols / 2 + 0.5) * px
    chord = lambda r, c=0.0: 2 * np.sqrt(np.maximum(r * r - (s[None] - c) ** 2, 0))
    bg = 0.1 * chord(4.0) + 0.08 * (chord(4.3) - chord(4.0))
    data = np.repeat(bg, n, 0)
    for bx, by, r in [(0.5, 0.0, 0.45), (-0.5, 0.1, 0.4), (0.0, 0.9, 0.35), (0.1, -0.8, 0.4), (2.0, 1.0, 0.6)]:
        data = data - 0.1 * chord(r, bx * np.cos(th)[:, None] + by * np.sin(th)[:, None])
    data += 0.003 * np.random.default_rng(3).normal(size=data.shape)
    central = np.abs(s) < 0.3
    est = radial_background(data.astype(np.float32), g)
    env = envelope_background(data)
    inside = np.abs(s) < 3.8
    assert np.abs(est - bg[0])[inside].max() < 0.01
    assert np.abs(env - bg[0])[central].mean() > 0.03  # the envelope misses the centre
