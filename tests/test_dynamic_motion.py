"""Warm starts predicted from each track's last step: displacement and growth measured at a warm fit."""

import numpy as np
import pytest

from bubsub.clients.pipeline.dynamic4d.chain import BubbleState, DynamicSettings, _warm_starts
from bubsub.clients.pipeline.dynamic4d.motion import MIN_STEPS, START_MARGIN, measure_steps, predict
from bubsub.core import ScanGeometry, sphere_surface

MU = -0.1
# 32 rows of 0.05 mm: the detector's top and bottom planes at z = +-0.8 mm
GEOMETRY = ScanGeometry.parallel(np.linspace(0, np.pi, 12, endpoint=False), pixel_size=0.05, cols=64, rows=32)


def _balls(centres, radii):
    return [sphere_surface(c, r, MU, control=42, levels=1) for c, r in zip(centres, radii)]


def test_steps_are_the_displacement_and_radius_ratio_of_bubbles_wholly_in_view():
    centres = np.array([[-0.8, 0.0, 0.0], [0.0, 0.5, -0.2], [0.7, -0.3, 0.2], [0.0, -0.6, 0.7]])
    before = _balls(centres, [0.2, 0.25, 0.15, 0.2])  # the last is cut by the top plane
    shift = np.array([0.01, -0.02, -0.05])
    after = _balls(centres[:3] + shift, [0.18, 0.25, 0.165]) + _balls([[0.0, 0.0, 0.0]], [0.1])
    steps = measure_steps([5, 6, 7, 8], before, [7, 5, 6, 9], [after[2], after[0], after[1], after[3]], GEOMETRY)
    assert steps[3] is None  # new here
    for step, ratio in zip(steps[:3], (1.1, 0.9, 1.0)):
        np.testing.assert_allclose(step[:3], shift, atol=2e-3)
        assert step[3] == pytest.approx(ratio, rel=0.02)
    # the bubble cut by the top plane: its centroid lies toward the unseen part, no step
    moved = _balls(centres[3:] + shift, [0.2])
    assert measure_steps([8], before[3:], [8], moved, GEOMETRY) == (None,)


def test_prediction_takes_the_neighbours_median_displacement_and_the_bubbles_own_growth():
    rng = np.random.default_rng(0)
    centres = rng.uniform(-0.6, 0.6, (12, 3))
    surfaces = _balls(centres, np.full(12, 0.1))
    flow = np.array([0.0, 0.0, -0.048])
    steps = [tuple(flow + rng.normal(0, 0.002, 3)) + (1.0 + 0.01 * k,) for k in range(12)]
    steps[4] = tuple(flow + [0.3, 0.0, 0.0]) + (1.0,)  # one outlier among the neighbours: the median ignores it
    steps[7] = None  # not measured: its neighbours' median ratio
    shifts, ratios = predict(surfaces, tuple(steps))
    np.testing.assert_allclose(shifts, np.tile(flow, (12, 1)), atol=0.01)
    assert ratios[3] == pytest.approx(1.03) and 1.0 <= ratios[7] <= 1.11
    # too few measured bubbles predict nothing
    few = tuple(s if k < MIN_STEPS - 1 else None for k, s in enumerate(steps))
    shifts, ratios = predict(surfaces, few)
    assert not shifts.any() and np.isnan(ratios).all()
    assert not predict(surfaces, ())[0].any()


def test_a_warm_start_is_moved_by_the_predicted_step_and_scaled_to_its_predicted_size():
    class Scan:
        geometry, ndim, bubble_contrast = GEOMETRY, 3, MU

    centres = np.array([[-0.5, 0.0, 0.0], [0.0, 0.4, 0.1], [0.5, -0.2, -0.1], [0.1, -0.5, 0.2]])
    surfaces = _balls(centres, [0.15, 0.2, 0.12, 0.18])
    step = (0.0, 0.0, -0.05, 1.0)
    settings = DynamicSettings(progress=False)
    plain = BubbleState.from_surfaces([1, 2, 3, 4], surfaces, MU)
    moving = BubbleState.from_surfaces([1, 2, 3, 4], surfaces, MU, steps=(step,) * 4)
    _, starts, _ = _warm_starts(Scan, plain, plain.surfaces(), settings)
    _, moved, _ = _warm_starts(Scan, moving, moving.surfaces(), settings)
    for s, a, b in zip(surfaces, starts, moved):
        c, r = np.asarray(s.fine().centroid), s.fine().equivalent_radius
        np.testing.assert_allclose(a.fine().centroid, c, atol=2e-3)  # shrunk in place
        np.testing.assert_allclose(b.fine().centroid, c + step[:3], atol=2e-3)
        assert a.fine().equivalent_radius == pytest.approx(settings.shrink * r, rel=0.03)
        assert b.fine().equivalent_radius == pytest.approx(START_MARGIN * r, rel=0.03)
