"""Each bubble subdivided by its size on the detector (clients/pipeline/static/resolution.py)."""

import numpy as np
import pytest

from bubsub.core import ScanGeometry, circle_surface, sphere_surface
from bubsub.clients.pipeline.dynamic4d.chain import BubbleState, SubscanResult
from bubsub.clients.pipeline.dynamic4d.outputs4d import read_subscan_result, write_subscan
from bubsub.clients.pipeline.static.resolution import (FACET_PIXELS, facet_depth, level_counts, levels_by_size,
                                                       pixels_per_mm)

PIXEL = 0.012
ANGLES = np.linspace(0, np.pi, 12, endpoint=False)


def parallel():
    return ScanGeometry.parallel(ANGLES, pixel_size=PIXEL, cols=256, rows=96)


def test_pixels_per_mm_is_the_inverse_pixel_in_parallel_beam_and_the_magnification_in_cone_beam():
    points = np.array([[0.0, 0.0, 0.0], [0.4, -0.3, 0.2]])
    assert np.allclose(pixels_per_mm(parallel(), points), 1 / PIXEL)
    cone = ScanGeometry.cone(ANGLES, source_origin=50.0, origin_detector=150.0, pixel_size=0.05, cols=256, rows=96)
    # a point on the rotation axis is magnified (50 + 150) / 50 = 4 times in every view
    assert pixels_per_mm(cone, points[:1])[0] == pytest.approx(4 / 0.05, rel=1e-6)
    # off the axis the magnification changes from view to view: the mean lies between its extremes
    d = np.hypot(0.4, 0.3)
    lo, hi = 200 / (50 + d) / 0.05, 200 / (50 - d) / 0.05
    assert lo < pixels_per_mm(cone, points[1:])[0] < hi


@pytest.mark.parametrize("control", [12, 42, 162])
def test_facet_depth_bounds_the_fine_mesh_distance_from_the_sphere(control):
    # independent truth: the fine mesh's faces measured
    r_px = 20.0
    s = sphere_surface(np.zeros(3), r_px * PIXEL, -0.1, control=control, levels=2)
    for levels in (0, 1, 2):
        fine = s.with_levels(levels).fine()
        v, f = fine.vertices, fine.faces
        # each face's centre below the sphere through its own corners (the centre sits deepest)
        corners = np.linalg.norm(v[f], axis=2).mean(axis=1)
        depth = (corners - np.linalg.norm(v[f].mean(axis=1), axis=1)).max() / PIXEL
        estimate = facet_depth(s, levels, 1 / PIXEL)
        assert 0.3 * depth < estimate < 1.5 * depth, (levels, depth, estimate)


def test_levels_follow_the_size_on_the_detector():
    g = parallel()
    radii_px = [8.0, 15.0, 30.0, 60.0]
    spheres = [sphere_surface([0.0, 0.0, 0.0], r * PIXEL, -0.1, levels=2) for r in radii_px]
    chosen = levels_by_size(spheres, g, 2)
    assert [s.levels for s in chosen] == [1, 1, 2, 2]
    for s in chosen:  # the fewest levels within the tolerance (one at least)
        depth = facet_depth(s, s.levels, 1 / PIXEL)
        assert depth <= FACET_PIXELS or s.levels == 2
        assert s.levels == 1 or facet_depth(s, s.levels - 1, 1 / PIXEL) > FACET_PIXELS
    # a coarser detector sees the same bubbles smaller
    binned = ScanGeometry.parallel(ANGLES, pixel_size=4 * PIXEL, cols=64, rows=24)
    assert [s.levels for s in levels_by_size(spheres, binned, 2)] == [1, 1, 1, 1]
    # more levels allowed: only the largest bubble, on a fine detector, takes them
    assert [s.levels for s in levels_by_size(spheres, g, 3)] == [1, 1, 2, 2]
    assert [s.levels for s in levels_by_size(spheres, g, 3, tolerance=0.05)] == [2, 2, 3, 3]
    # off: every bubble at the most levels; and never more than asked
    assert [s.levels for s in levels_by_size(spheres, g, 2, tolerance=0)] == [2, 2, 2, 2]
    assert [s.levels for s in levels_by_size(spheres, g, 0)] == [0, 0, 0, 0]
    assert level_counts(chosen) == {"1": 2, "2": 2}
    assert level_counts(levels_by_size(spheres[:1], g, 0)) == {"0": 1}
    # 2D bubbles keep their levels
    g2 = ScanGeometry.parallel(ANGLES, pixel_size=PIXEL, cols=256)
    circles = [circle_surface([0.0, 0.0], 8 * PIXEL, -0.1, levels=2)]
    assert levels_by_size(circles, g2, 2)[0] is circles[0]
    with pytest.raises(ValueError, match="facet tolerance"):
        levels_by_size(spheres, g, 2, tolerance=-1.0)


def test_a_new_level_keeps_the_fine_mesh_mean_radius_and_centre():
    rng = np.random.default_rng(3)
    s = sphere_surface([0.2, -0.1, 0.3], 0.25, -0.1, levels=2)
    s = s.with_vertices(s.vertices * np.array([1.3, 1.0, 0.8]) + 0.01 * rng.standard_normal(s.vertices.shape))

    def radius(x):
        v = x.fine().vertices
        return np.linalg.norm(v - v.mean(axis=0), axis=1).mean()

    for levels in (0, 1, 3):
        t = s.with_levels(levels, keep_size=True)
        assert t.levels == levels
        assert radius(t) == pytest.approx(radius(s), rel=1e-12)
        assert np.allclose(t.vertices.mean(axis=0), s.vertices.mean(axis=0))
    assert abs(radius(s.with_levels(1)) / radius(s) - 1) > 1e-3  # without the scaling the size would change
    assert s.with_levels(2, keep_size=True) is s


def test_a_subscan_folder_keeps_each_bubbles_levels(tmp_path):
    surfaces = [sphere_surface([0.0, 0.0, 0.0], 0.3, -0.1, levels=2),
                sphere_surface([0.8, 0.0, 0.0], 0.1, -0.1, levels=1)]
    state = BubbleState.from_surfaces([4, 9], surfaces)
    assert state.levels == (2, 1)
    assert [s.levels for s in state.surfaces()] == [2, 1]
    result = SubscanResult(3, 1.5, state, (), {"start": "cold", "bubbles": 2, "time": 1.5})
    write_subscan(tmp_path, result, 3)
    back = read_subscan_result(tmp_path, 3, -0.1)
    assert back.state.levels == (2, 1) and back.state.ids == (4, 9)
    for a, b in zip(back.state.surfaces(), surfaces):
        assert np.allclose(a.fine().vertices, b.fine().vertices)
