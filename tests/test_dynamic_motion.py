"""Warm starts predicted from each track's last step: displacement and growth measured at a warm fit; the flow
followed during a subscan."""

import numpy as np
import pytest

from bubsub.clients.pipeline.dynamic4d.chain import BubbleState, DynamicSettings, _flow, _warm_starts
from bubsub.clients.optimise.fit import fit
from bubsub.clients.pipeline.dynamic4d.motion import (MIN_STEPS, START_MARGIN, flow_during, flow_in_data, measure_steps,
                                                         predict)
from bubsub.core import MeshProjector, ScanGeometry, sphere_surface
from bubsub.core.io.scan import Scan
from bubsub.core.projection.mesh import Mesh

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


def test_the_flow_during_a_subscan_is_minus_the_median_step_spread_over_its_projections():
    step = (0.0, 0.01, -0.15, 1.0)  # going backwards in time the foam moved 0.15 mm down
    steps = (step, None, step, (0.3, 0.0, -0.15, 1.0), step)
    flow = flow_during(steps, 10)
    assert flow.shape == (10, 3)
    fraction = (np.arange(10) - 4.5) / 10  # the subscan spans ten projection intervals, its middle at 4.5
    np.testing.assert_allclose(flow, fraction[:, None] * np.array([[0.0, -0.01, 0.15]]), atol=1e-12)
    # the times decide where each projection stands in the subscan
    times = np.array([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 18.0])  # a pause before the last
    uneven = flow_during(steps, 10, times)
    np.testing.assert_allclose(uneven[:, 2], 0.15 * (times - 9.0) / 20.0, atol=1e-12)
    assert flow_during(steps[:1] + (None,) * 4, 10) is None  # fewer than MIN_STEPS measured
    assert flow_during((), 10) is None


def test_a_bubble_moving_during_a_subscan_is_fitted_where_it_stands_at_the_mid_time():
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 24, endpoint=False), pixel_size=0.05, cols=64, rows=32)
    centre = np.array([0.1, 0.0, 0.55])  # near the top plane (z = 0.8), rising 0.15 mm over the subscan
    steps = ((0.0, 0.0, -0.15, 1.0),) * MIN_STEPS
    flow = flow_during(steps, 24)
    ico = __import__("trimesh").creation.icosphere(subdivisions=3)
    rng = np.random.default_rng(3)
    data = np.stack([MeshProjector(g[k:k + 1]).forward(
        Mesh(np.asarray(ico.vertices) * 0.3 + centre + flow[k], np.asarray(ico.faces), MU))[0] for k in range(24)])
    data = (data + rng.normal(0, 0.002, data.shape)).astype(np.float32)
    start = [sphere_surface(centre - [0.0, 0.0, 0.05], 0.27, MU, control=42, levels=2)]
    followed = fit(MeshProjector(g.moved(flow)), start, data, iterations=60, progress=False)
    still = fit(MeshProjector(g), start, data, iterations=60, progress=False)
    np.testing.assert_allclose(followed.surfaces[0].fine().centroid, centre, atol=0.01)
    assert followed.surfaces[0].fine().equivalent_radius == pytest.approx(0.3, rel=0.03)
    assert followed.objective < 0.5 * still.objective  # standing still, the fit cannot explain the motion


def _moving_foam(geometry, flow, centres, radii):
    """Projections of icosphere bubbles displaced by ``flow[k]`` at projection ``k``, with fixed-seed noise."""
    ico = __import__("trimesh").creation.icosphere(subdivisions=3)
    balls = lambda d: [Mesh(np.asarray(ico.vertices) * r + c + d, np.asarray(ico.faces), MU)
                       for c, r in zip(centres, radii)]
    data = np.stack([MeshProjector(geometry[k:k + 1]).forward(balls(flow[k]))[0] for k in range(len(flow))])
    return (data + np.random.default_rng(4).normal(0, 0.002, data.shape)).astype(np.float32)


def test_the_flow_along_the_axis_is_measured_from_the_data_row_sums():
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 24, endpoint=False), pixel_size=0.05, cols=64, rows=32)
    rng = np.random.default_rng(2)
    centres = np.column_stack([rng.uniform(-0.8, 0.8, (10, 2)), rng.uniform(-0.9, 0.9, 10)])
    radii = rng.uniform(0.12, 0.25, 10)
    true = flow_during(((0.0, 0.0, -0.12, 1.0),) * MIN_STEPS, 24)  # 2.4 rows up over the subscan
    data = _moving_foam(g, true, centres, radii)
    measured = flow_in_data(data, g, MU)
    np.testing.assert_allclose(measured[:, :2], 0.0, atol=1e-12)  # only the axial component is measured
    np.testing.assert_allclose(measured[:, 2], true[:, 2], atol=0.06 * 0.12)
    # a foam standing still measures about none
    still = flow_in_data(_moving_foam(g, np.zeros((24, 3)), centres, radii), g, MU)
    assert np.abs(still).max() < 0.05 * 0.12
    # nothing where the row sums depend on the angle: a cone beam, signal at the detector's side
    cone = ScanGeometry.cone(np.linspace(0, np.pi, 24, endpoint=False), source_origin=40.0, origin_detector=10.0,
                             pixel_size=0.05, cols=64, rows=32)
    assert flow_in_data(data, cone, MU) is None
    wide = _moving_foam(g, true, np.vstack([centres, [[1.5, 0.0, 0.0]]]), np.append(radii, 0.3))
    assert flow_in_data(wide, g, MU) is None


def test_a_subscan_follows_its_tracks_flow_else_the_datas_else_none():
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 24, endpoint=False), pixel_size=0.05, cols=64, rows=32)
    rng = np.random.default_rng(2)
    centres = np.column_stack([rng.uniform(-0.8, 0.8, (10, 2)), rng.uniform(-0.9, 0.9, 10)])
    true = flow_during(((0.0, 0.0, -0.12, 1.0),) * MIN_STEPS, 24)
    scan = Scan(data=_moving_foam(g, true, centres, rng.uniform(0.12, 0.25, 10)), geometry=g, bubble_contrast=MU,
                time=np.linspace(10.0, 12.3, 24))
    settings = DynamicSettings(progress=False)
    flow, source = _flow(scan, None, settings)  # the cold start: the data's row sums
    assert source == "data"
    np.testing.assert_allclose(flow[:, 2], true[:, 2], atol=0.06 * 0.12)
    surfaces = _balls(centres, np.full(10, 0.1))
    lateral = ((0.02, 0.0, -0.1, 1.0),) * 10
    previous = BubbleState.from_surfaces(range(10), surfaces, MU, steps=lateral)
    flow, source = _flow(scan, previous, settings)  # the tracks' steps first, across the axis too
    assert source == "tracks"
    np.testing.assert_allclose(flow[-1] - flow[0], np.array([-0.02, 0.0, 0.1]) * 23 / 24, atol=1e-9)
    assert _flow(scan, previous, DynamicSettings(follow_flow=False, progress=False)) == (None, None)
