"""Coarse to fine in the data: binned detectors, and the fit level by level."""

import numpy as np
import pytest

from bubsub.core import MeshProjector, ScanGeometry, sphere_surface
from bubsub.core.projection.subdivision import circle_surface
from bubsub.clients.optimise.fit import fit
from bubsub.clients.optimise.levels import bin_factors, coarse_surfaces, fit_levels, level_rtol

ANGLES = np.linspace(0, np.pi, 6, endpoint=False)


@pytest.mark.parametrize("kind", ["parallel", "cone", "2d"])
def test_a_binned_detector_sees_the_mean_of_the_pixels_it_joins(kind):
    if kind == "parallel":
        g, b = ScanGeometry.parallel(ANGLES, pixel_size=0.05, cols=61, rows=43), sphere_surface([0.2, 0.1, 0.1], 0.5, -0.1)
    elif kind == "cone":
        g = ScanGeometry.cone(ANGLES, source_origin=30.0, origin_detector=10.0, pixel_size=0.05, cols=61, rows=43)
        b = sphere_surface([0.2, 0.1, 0.1], 0.5, -0.1)
    else:
        g, b = ScanGeometry.parallel(ANGLES, pixel_size=0.05, cols=61), circle_surface([0.2, 0.1], 0.5, -0.1)
    binned = g.binned(2)
    assert binned.det_cols == 30 and (g.ndim == 2 or binned.det_rows == 21)
    # 2 x 2 sub-rays of each fine pixel are 4 x 4 of the binned one, at the same places
    fine = MeshProjector(g, supersampling=2).forward([b])
    coarse = MeshProjector(binned, supersampling=4).forward([b])
    assert np.abs(fine).max() > 0.05
    np.testing.assert_allclose(coarse, ScanGeometry.bin_projections(fine, 2), atol=1e-6)
    assert g.binned(1) is g
    with pytest.raises(ValueError, match="cannot bin"):
        g.binned(100)


def test_bin_factors():
    big = ScanGeometry.parallel(ANGLES, pixel_size=0.05, cols=256, rows=128)
    small = ScanGeometry.parallel(ANGLES, pixel_size=0.05, cols=256, rows=64)
    assert bin_factors(big) == [2, 1] and bin_factors(small) == [1]
    assert bin_factors(ScanGeometry.parallel(ANGLES, pixel_size=0.05, cols=2000)) == [1]
    assert bin_factors(small, 3) == [4, 2, 1]
    with pytest.raises(ValueError, match="positive integer"):
        bin_factors(big, 0)


def _scene():
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 10, endpoint=False), pixel_size=0.05, cols=64, rows=48)
    truth = [sphere_surface([0.3, 0.1, 0.2], 0.45, -0.1, control=162, levels=2),
             sphere_surface([-0.5, -0.2, -0.3], 0.35, -0.1, control=162, levels=2)]
    data = MeshProjector(g, supersampling=2).forward(truth)
    data = data + np.random.default_rng(0).normal(0, 0.003, data.shape).astype(np.float32)  # a noise floor
    start = [sphere_surface([0.25, 0.15, 0.15], 0.38, -0.1), sphere_surface([-0.45, -0.25, -0.25], 0.3, -0.1)]
    return g, data, start


def test_fit_levels_reports_each_level_and_reaches_the_full_resolution_fit():
    g, data, start = _scene()
    P = MeshProjector(g)
    result, levels = fit_levels(P, start, data, factors=[2, 1], iterations=40, rtol=1e-4)
    assert [lv["bin"] for lv in levels] == [2, 1] and levels[0]["detector"] == [24, 32]
    assert result.iterations == sum(lv["iterations"] for lv in levels)
    assert result.evaluations == sum(lv["evaluations"] for lv in levels)
    # the binned level fits one Loop step fewer; the result is at the surfaces' own subdivision
    assert [lv["subdivision"] for lv in levels] == [1, 2] and [s.levels for s in result.surfaces] == [2, 2]
    assert all(lv["stop_reason"] in ("converged", "iteration limit") and lv["seconds"] > 0 for lv in levels)
    reference = fit(P, start, data, iterations=150, progress=False)
    f0 = float(P.objective(start, data)[0])
    assert result.objective < 0.2 * f0
    # the bar: within 1 % of a long fit on the full detector
    assert result.objective <= 1.01 * reference.objective


def test_coarse_surfaces_drop_a_loop_step_per_binning_and_keep_the_control_vertices():
    s = [sphere_surface([0, 0, 0], 0.4, -0.1, levels=n) for n in (3, 2, 1, 0)]
    levels = [x.levels for x in s]
    for factor, want in ((1, [3, 2, 1, 0]), (2, [2, 1, 1, 0]), (4, [1, 1, 1, 0])):
        out = coarse_surfaces(s, factor, levels)
        assert [x.levels for x in out] == want
        assert all(np.array_equal(x.vertices, y.vertices) for x, y in zip(out, s))
    back = coarse_surfaces(coarse_surfaces(s, 4, levels), 1, levels)
    assert [x.levels for x in back] == levels
    # a projected face of the coarse surface covers about as many binned pixels as the fine one full pixels
    assert len(coarse_surfaces(s[:1], 2, [3])[0].fine().faces) * 4 == len(s[0].fine().faces)


def test_rtol_ends_a_stalled_fit_before_its_cap():
    g, data, start = _scene()
    P = MeshProjector(g)
    capped = fit(P, start, data, iterations=60, progress=False, method="lbfgs")
    stopped = fit(P, start, data, iterations=60, progress=False, method="lbfgs", rtol=1e-2)
    assert capped.stop_reason == "iteration limit" and capped.iterations == 60
    assert stopped.stop_reason == "converged" and stopped.iterations < 60
    h = [x["objective"] for x in stopped.history]
    assert h[-6] - h[-1] <= 1e-2 * h[-1]


def test_a_binned_level_is_held_to_the_full_detectors_relative_progress():
    # the premise of level_rtol: binning by f divides the noise floor by f^4 and a move's fall by about f^2
    g, _, start = _scene()
    truth = [s.with_vertices(s.vertices + [0.02, 0.0, 0.01]) for s in start]
    P, Pb = MeshProjector(g, supersampling=2), MeshProjector(g.binned(2), supersampling=2)
    noise = np.random.default_rng(1).normal(0, 0.003, g.shape)
    half_sq = lambda a: 0.5 * float(np.vdot(a, a))  # noqa: E731
    assert half_sq(ScanGeometry.bin_projections(noise, 2)) / half_sq(noise) == pytest.approx(1 / 16, rel=0.1)
    fall = half_sq(P.forward(start) - P.forward(truth))
    fall_binned = half_sq(Pb.forward(start) - Pb.forward(truth))
    # about 1/f^2, a little less: the mean of f^2 pixels smooths a change finer than itself
    assert 0.15 < fall_binned / fall <= 0.25 * 1.05
    assert level_rtol(2e-4, 2) == pytest.approx(8e-4) and level_rtol(2e-4, 1) == 2e-4 and level_rtol(None, 2) is None
