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


def _scan(seed, cols=96, pixel=0.02, axis=49.3):
    """Exact projections (90 views over 180 degrees, noise 0.003) of a liquid disc (0.1/mm) 1.5 times the field
    of view's radius, filled out to its wall with disjoint gas discs (random sequential addition):
    ``data, liquid's projection, geometry, field of view's radius, true gas fraction inside it``."""
    g = scan_geometry(np.linspace(0, 180, 90, endpoint=False), pixel_size=(pixel, pixel), cols=cols,
                      axis_column=axis)
    fov = min(axis + 0.5, cols - 0.5 - axis) * pixel
    radius = 1.5 * fov
    rng = np.random.default_rng(seed)
    centres, radii = np.empty((0, 2)), np.empty(0)
    for c, q in zip(rng.uniform(-radius, radius, (20000, 2)), rng.uniform(0.08, 0.16, 20000) * fov):
        if np.hypot(*c) + q < radius and np.all(np.hypot(*(centres - c).T) > q + radii + 0.01):
            centres, radii = np.vstack([centres, c]), np.append(radii, q)
    discs = list(zip(centres, radii))
    projector = MeshProjector(g, supersampling=2)
    liquid = projector.forward([_disc((0, 0), radius, 0.1)])[0]
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
