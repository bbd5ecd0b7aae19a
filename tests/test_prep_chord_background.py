"""The background of a liquid cylinder wider than the detector (local tomography), on exact projections of a
foam filling it: the liquid's chord profile, fitted to the mean projection less the gas that a reconstruction
shows inside the field of view, against the liquid's own projection; and the liquid's attenuation, the bubbles'
contrast and the gas fraction inside the field of view found on the way."""

import numpy as np
import pytest

from bubsub.core import MeshProjector
from bubsub.core.prep.background import chord_background, detector_offsets
from bubsub.core.prep.pipeline import scan_geometry
from bubsub.core.projection.mesh import Polygon

T = np.linspace(0, 2 * np.pi, 64, endpoint=False)


def _disc(centre, radius, attenuation):
    return Polygon(np.asarray(centre) + radius * np.stack([np.cos(T), np.sin(T)], 1) / np.cos(np.pi / 64),
                   attenuation)


def _gas_discs(rng, reach, fov):
    """Disjoint gas discs (radii 0.08-0.16 of ``fov``, films of 0.01 mm) inside ``reach`` mm of the axis, by random
    sequential addition: a list of ``(centre, radius)``."""
    centres, radii = np.empty((0, 2)), np.empty(0)
    for c, q in zip(rng.uniform(-reach, reach, (20000, 2)), rng.uniform(0.08, 0.16, 20000) * fov):
        if np.hypot(*c) + q < reach and np.all(np.hypot(*(centres - c).T) > q + radii + 0.01):
            centres, radii = np.vstack([centres, c]), np.append(radii, q)
    return list(zip(centres, radii))


def _liquid_and_discs(seed, inside_only, cols, pixel, axis):
    """90 views over 180 degrees of ``cols`` columns, a liquid disc (0.1/mm) 1.5 times the field of view's radius
    and its gas discs (:func:`_gas_discs`) out to its wall, or ``inside_only`` the field of view: ``geometry,
    field of view's radius, liquid's radius, the random generator, the discs, a projector, the liquid's
    projection``."""
    g = scan_geometry(np.linspace(0, 180, 90, endpoint=False), pixel_size=(pixel, pixel), cols=cols,
                      axis_column=axis)
    fov = min(axis + 0.5, cols - 0.5 - axis) * pixel
    radius = 1.5 * fov
    rng = np.random.default_rng(seed)
    discs = _gas_discs(rng, fov if inside_only else radius, fov)
    projector = MeshProjector(g, supersampling=2)
    return g, fov, radius, rng, discs, projector, projector.forward([_disc((0, 0), radius, 0.1)])[0]


def _scan(seed, cols=96, pixel=0.02, axis=49.3):
    """Exact projections (90 views over 180 degrees, noise 0.003) of a liquid disc (0.1/mm) 1.5 times the field
    of view's radius, filled out to its wall with disjoint gas discs (random sequential addition):
    ``data, liquid's projection, geometry, field of view's radius, true gas fraction inside it``."""
    g, fov, radius, rng, discs, projector, liquid = _liquid_and_discs(seed, False, cols, pixel, axis)
    data = liquid + projector.forward([_disc(c, q, -0.1) for c, q in discs])
    data += rng.normal(0, 0.003, data.shape)
    s = detector_offsets(g)
    assert np.allclose(liquid, 0.2 * np.sqrt(np.maximum(radius ** 2 - s ** 2, 0)), atol=2e-3)  # the truth
    x = np.linspace(-fov, fov, 601)
    inside = np.hypot(*np.meshgrid(x, x)) <= fov
    gas = np.zeros_like(inside)
    for c, q in discs:  # each disc on the grid within its bounding box
        i0, i1 = np.searchsorted(x, c[0] - q), np.searchsorted(x, c[0] + q)
        j0, j1 = np.searchsorted(x, c[1] - q), np.searchsorted(x, c[1] + q)
        if i1 > i0 and j1 > j0:
            gas[j0:j1, i0:i1] |= np.hypot(*np.meshgrid(x[i0:i1] - c[0], x[j0:j1] - c[1])) < q
    return data.astype(np.float32), liquid, g, fov, float(gas[inside].mean())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_liquids_projection_is_fitted_with_the_gas_inside_the_field_of_view_taken_out(seed):
    data, liquid, g, fov, gas_fraction = _scan(seed)
    bg, fit = chord_background(data, g)
    assert np.abs(bg - liquid).mean() < 0.05 * liquid.max()  # 0.037, 0.014, 0.005 of it
    assert fit["liquid_attenuation"] == pytest.approx(0.1, rel=0.06)
    assert fit["contrast"] == pytest.approx(-0.1, rel=0.1)
    assert fit["gas_fraction"] == pytest.approx(gas_fraction, abs=0.05)


def _annulus_scan(seed, outer, cols=96, pixel=0.02, axis=49.3):
    """Exact projections (90 views, noise 0.003) of a liquid disc (0.1/mm) 1.5 times the field of view's radius:
    disjoint gas discs (random sequential addition) inside the field of view, and beyond it out to the wall a
    uniform gas fraction ``outer`` (an annulus of attenuation ``-0.1 outer``): ``data, liquid's projection,
    geometry, liquid's radius``."""
    g, fov, radius, rng, discs, projector, liquid = _liquid_and_discs(seed, True, cols, pixel, axis)
    annulus = projector.forward([_disc((0, 0), radius, -0.1 * outer), _disc((0, 0), fov, 0.1 * outer)])
    data = liquid + annulus + projector.forward([_disc(c, q, -0.1) for c, q in discs])
    data += rng.normal(0, 0.003, data.shape)
    return data.astype(np.float32), liquid, g, radius


@pytest.mark.parametrize("seed, outer", [(0, 0.15), (1, 0.3)])
def test_given_the_liquids_radius_the_foam_beyond_the_field_of_view_has_its_own_gas_fraction(seed, outer):
    # the field of view holds about 0.48 of gas: the fitted radius with the inside's gas fraction beyond (the
    # default) takes the lighter foam there for a wider cylinder, the given radius leaves it to its own fraction
    data, liquid, g, radius = _annulus_scan(seed, outer)
    bg, fit = chord_background(data, g, radius=radius)
    assert fit["radius_mm"] == radius
    assert fit["outer_gas_fraction"] == pytest.approx(outer, abs=0.06)  # 0.10 and 0.26: the inside's
    assert fit["liquid_attenuation"] == pytest.approx(0.1, rel=0.06)    # gas a little overestimated (0.095, 0.096)
    error = np.abs(bg - liquid).mean()
    assert error < 0.05 * liquid.max()  # 0.047, 0.038 of it
    assert np.abs(chord_background(data, g)[0] - liquid).mean() > 5 * error


def test_a_given_radius_within_the_detectors_reach_is_refused():
    data, _, g, radius = _annulus_scan(0, 0.3)
    with pytest.raises(ValueError, match="liquid-radius"):
        chord_background(data, g, radius=0.95 * radius / 1.5)


def test_prepare_takes_the_liquids_radius_as_a_positive_length():
    from bubsub.core.prep import prepare_options

    assert prepare_options(liquid_radius=2.5).liquid_radius == 2.5
    with pytest.raises(ValueError, match="liquid_radius must be a positive number"):
        prepare_options(liquid_radius=-1.0)


@pytest.fixture(scope="module")
def thinning_raw(tmp_path_factory):
    """A simulated raw beamline scan (flats, darks, Fresnel propagation at 16 keV over 300 mm) of a liquid cylinder
    1.5 times the field of view's radius, filled with bubbles out to its wall: its foam beyond the field of view
    holds less gas than inside, which a fitted radius takes for a wider cylinder. ``(folder, settings)``."""
    from bubsub.core.foam.raw import disc_foam, raw_settings, write_raw_simulation

    out = tmp_path_factory.mktemp("thinning")
    c = {"cols": 128, "pixel_size": 0.024, "axis_offset": 2.3, "n_angles": 60, "rows": 2, "distance": 300.0}
    axis = c["cols"] / 2 - 0.5 + c["axis_offset"]
    fov = min(axis + 0.5, c["cols"] - 0.5 - axis) * c["pixel_size"]
    radius = 1.5 * fov
    s = raw_settings(seed=5, container_radius=radius, wall=0.0, wider_than_detector=True, supersample=2, **c)
    write_raw_simulation(out, disc_foam(5, radius, n_bubbles=80, radius_range=(0.08 * fov, 0.15 * fov)), s)
    return out, s


def test_prepare_with_the_liquids_radius_given_on_a_raw_scan_of_a_foam_thinning_beyond_the_field_of_view(
        thinning_raw, tmp_path):
    from bubsub.bench.local_truth import true_background
    from bubsub.core.io.scanfile import read_scan
    from bubsub.core.prep import prepare, prepare_options

    raw, s = thinning_raw
    radius = s.container_radius
    errors = {}
    for given in (None, radius):
        # the background model alone: without the pixel gains (--double-flat), which also set right two adjacent
        # dead columns that a one-row ROI's 1 x 3 median cannot repair, and so move the mean projection by 0.005
        report = prepare(raw / "raw.h5", tmp_path / "scan.h5", prepare_options(
            roi="1:2,:", delta_beta=1450, center=s.axis_column, background="auto", liquid_radius=given,
            double_flat="off"), progress=False)
        fit = next(x for x in report["steps"] if x["step"] == "background")["wider_than_detector"]
        scan = read_scan(tmp_path / "scan.h5")
        offsets = detector_offsets(scan.geometry)
        # the truth: the liquid's exact projection and the true bubbles' mean projection beyond the reach
        truth = sum(true_background(raw, s, offsets))
        errors[given] = np.abs(scan.background[0] - truth).mean()
    assert fit["radius_mm"] == pytest.approx(radius) and "radius given" in fit["method"]
    assert "foam beyond" in fit["method"] and fit["foam_beyond_at_axis"] < 0  # gas: less than the liquid
    assert fit["outer_gas_fraction"] < fit["gas_fraction"] - 0.05  # 0.36 against 0.46
    assert errors[radius] < 0.5 * errors[None]  # 0.011 against 0.030 (liquid's chord 0.44 at the axis)


def test_the_foam_beyond_the_reach_makes_the_background_nearly_independent_of_the_liquids_radius(thinning_raw,
                                                                                                 tmp_path):
    # the mean projection does not tell the liquid's radius from the outer foam's gas fraction: fitted, the radius
    # comes out 25 % large; the liquid's profile then moves with it, the liquid and the foam beyond together far less
    from bubsub.core.io.scanfile import read_scan
    from bubsub.core.prep import prepare, prepare_options
    from bubsub.core.prep.background import foam_beyond

    raw, s = thinning_raw
    prepare(raw / "raw.h5", tmp_path / "scan.h5", prepare_options(
        roi="1:2,:", delta_beta=1450, center=s.axis_column, background="none", double_flat="off"), progress=False)
    scan = read_scan(tmp_path / "scan.h5")
    (fitted, f1), (given, f2) = (chord_background(scan.data, scan.geometry, radius=x)
                                 for x in (None, s.container_radius))
    assert f1["radius_mm"] > 1.15 * s.container_radius
    liquid = fitted - given
    whole = fitted + foam_beyond(f1, scan.geometry) - given - foam_beyond(f2, scan.geometry)
    assert abs(whole.mean()) < 0.3 * abs(liquid.mean())  # 0.019 against 0.087
    assert whole.std() < 0.7 * liquid.std()  # the profile's shape: 0.0043 against 0.0080
    with pytest.raises(ValueError, match="reach must exceed"):
        foam_beyond(f1, scan.geometry, reach=1.0)
    assert not foam_beyond(f2, scan.geometry, reach=3.0).any()  # the wall within 3 field-of-view radii: nothing beyond
