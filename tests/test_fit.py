import numpy as np
import pytest

from bubsub.clients.optimise.fit import estimate_radii, fit
from bubsub.core import MeshProjector, Polygon, ScanGeometry, circle_surface, sphere_surface


@pytest.fixture(scope="module")
def scene2d():
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 20, endpoint=False), pixel_size=0.02, cols=240)
    a = np.linspace(0, 2 * np.pi, 256, endpoint=False)
    truth = [
        Polygon(np.c_[0.5 * np.cos(a) * (1 + 0.1 * np.cos(3 * a)), 0.5 * np.sin(a)] + [0.9, 0.3], -0.1),
        Polygon(np.c_[0.7 * np.cos(a), 0.55 * np.sin(a)] + [-1.0, -0.5], -0.1),
    ]
    P = MeshProjector(g, supersampling=2)
    return P, truth, P.forward(truth)


def test_fit_recovers_shapes_from_a_rough_start(scene2d):
    P, truth, data = scene2d
    init = [circle_surface([0.8, 0.4], 0.35, -0.1), circle_surface([-0.9, -0.4], 0.35, -0.1)]
    init = estimate_radii(P, init, data)
    res = fit(P, init, data, iterations=80, progress=False)
    f0 = P.objective(init, data)[0]
    assert res.objective < 1e-3 * f0
    assert res.iterations > 5 and res.history[-1]["objective"] <= res.history[0]["objective"]
    for s, t in zip(res.surfaces, truth):
        fine = s.fine()
        assert fine.area == pytest.approx(t.area, rel=0.01)
        np.testing.assert_allclose(fine.centroid, t.centroid, atol=0.01)


def test_radius_estimation_finds_the_radius():
    g = ScanGeometry.cone(np.linspace(0, 2 * np.pi, 8, endpoint=False), source_origin=300, origin_detector=15,
                          pixel_size=0.05, cols=80, rows=64)
    P = MeshProjector(g)
    truth = [sphere_surface([0.3, 0.0, 0.1], 0.9, -0.1), sphere_surface([-0.9, 0.2, -0.2], 0.5, -0.1)]
    data = P.forward(truth)
    start = [sphere_surface([0.3, 0.0, 0.1], 0.5, -0.1), sphere_surface([-0.9, 0.2, -0.2], 0.8, -0.1)]
    est = estimate_radii(P, start, data, iterations=30)
    for s, r in zip(est, (0.9, 0.5)):
        fine = s.fine().vertices
        assert np.linalg.norm(fine - fine.mean(axis=0), axis=1).mean() == pytest.approx(r, rel=0.01)


def test_radius_estimation_keeps_to_its_evaluation_cap(scene2d):
    P, truth, data = scene2d
    calls = []

    class Counting:
        def objective(self, surfaces, d):
            calls.append(1)
            return P.objective(surfaces, d)

    init = [circle_surface([0.9, 0.3], 0.2, -0.1), circle_surface([-1.0, -0.5], 1.2, -0.1)]
    f0 = P.objective(init, data)[0]
    est = estimate_radii(Counting(), init, data, iterations=3)
    assert 1 <= len(calls) <= 3 + 5
    assert P.objective(est, data)[0] < f0  # the best radii seen, not the last trial


def test_interrupt_returns_the_best_iterate(scene2d):
    P, truth, data = scene2d
    init = [circle_surface([0.9, 0.3], 0.5, -0.1), circle_surface([-1.0, -0.5], 0.6, -0.1)]
    seen = []

    def stop_after_three(k, f, surfaces):
        seen.append(f)
        if k == 3:
            raise KeyboardInterrupt

    res = fit(P, init, data, iterations=50, progress=False, callback=stop_after_three)
    assert res.interrupted and res.iterations == 3
    assert res.objective == pytest.approx(min(seen)) and res.objective < P.objective(init, data)[0]
    assert len(res.surfaces) == 2


def test_lbfgs_and_bfgs_both_descend(scene2d):
    P, truth, data = scene2d
    init = [circle_surface([0.9, 0.3], 0.5, -0.1), circle_surface([-1.0, -0.5], 0.6, -0.1)]
    f0 = P.objective(init, data)[0]
    for method in ("bfgs", "lbfgs"):
        res = fit(P, init, data, iterations=15, progress=False, method=method)
        assert res.method == method and res.objective < 0.1 * f0


def test_fit_refuses_bad_input(scene2d):
    P, truth, data = scene2d
    s = circle_surface([0, 0], 0.5, -0.1)
    with pytest.raises(ValueError, match="data is required"):
        fit(P, [s], None, progress=False)
    with pytest.raises(TypeError, match="SubdivisionSurface"):
        fit(P, truth, data, progress=False)
    with pytest.raises(ValueError, match="at least one"):
        fit(P, [], data, progress=False)
    with pytest.raises(ValueError, match="iterations"):
        fit(P, [s], data, iterations=-1, progress=False)
    with pytest.raises(ValueError, match="method"):
        fit(P, [s], data, method="newton", progress=False)
