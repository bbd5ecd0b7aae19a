"""Local refits: a change to a few bubbles is evaluated on their footprints only, the rest held fixed."""

import numpy as np

from bubsub.core import MeshProjector, ScanGeometry, sphere_surface
from bubsub.clients.pipeline.regions.local import local_refit, touching_groups

CENTRES = ((-1.2, -1.2, 0.0), (1.2, -1.2, 0.1), (-1.2, 1.2, -0.1), (1.2, 1.2, 0.0), (0.0, 0.0, 0.9))


def _scene():
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 12, endpoint=False), pixel_size=0.05, cols=96, rows=48)
    truth = [sphere_surface(c, 0.35, -0.1) for c in CENTRES]
    return g, truth, MeshProjector(g).forward(truth)


def test_touching_groups_join_neighbours_only():
    bubbles = [sphere_surface(c, 0.35, -0.1) for c in ((0, 0, 0), (0.75, 0, 0), (3, 0, 0))]
    assert touching_groups(bubbles, [0], 0.1) == [[0, 1]]
    assert touching_groups(bubbles, [2], 0.1) == [[2]]
    assert touching_groups(bubbles, [], 0.1, near=[((1.5, 0, 0), 0.5)]) == [[1]]


def test_changing_one_bubble_refits_it_on_its_footprint_only():
    g, truth, data = _scene()
    P = MeshProjector(g)
    moved = list(truth)
    moved[4] = sphere_surface((0.08, -0.05, 0.85), 0.3, -0.1)  # one bubble off its truth
    surfaces, residual, summary = local_refit(P, moved, data, [4], iterations=30, touch=0.05)
    assert summary["groups"] == 1 and summary["bubbles"] == 1
    assert all(surfaces[k] is moved[k] for k in range(4))  # the others are held fixed
    # the refit went to the truth ...
    assert np.linalg.norm(surfaces[4].fine().centroid - np.array(CENTRES[4])) < 0.01
    # ... evaluating a window of the detector around its shadow: much less than the whole scan per evaluation
    per_evaluation = summary["pixels"] / summary["evaluations"]
    assert per_evaluation < 0.4 * summary["scan_pixels"]
    # and the residual it returns is the whole scene's
    np.testing.assert_allclose(residual, P.forward(surfaces) - data, atol=2e-5)
    assert 0.5 * float(np.vdot(residual, residual)) < 0.05 * 0.5 * float(np.vdot(P.forward(moved) - data,
                                                                                  P.forward(moved) - data))


def test_changes_all_over_the_scan_are_refitted_at_once_on_the_whole_detector():
    # every bubble changed, on a coarse detector: five windows that together hold more pixels than the scan
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 12, endpoint=False), pixel_size=0.1, cols=48, rows=24)
    truth = [sphere_surface(c, 0.35, -0.1) for c in CENTRES[:4]] + [sphere_surface((0.0, 0.0, 0.5), 0.35, -0.1)]
    data = MeshProjector(g).forward(truth)
    P = MeshProjector(g)
    moved = [sphere_surface(t.fine().centroid + np.array([0.06, -0.05, 0.04]), 0.3, -0.1) for t in truth]
    surfaces, residual, summary = local_refit(P, moved, data, [0, 1, 2, 3, 4], iterations=40, touch=0.05)
    assert summary["groups"] == 5 and summary["joint"] and summary["bubbles"] == 5
    assert summary["pixels"] == summary["scan_pixels"] * summary["evaluations"]
    for s, t in zip(surfaces, truth):
        assert np.linalg.norm(s.fine().centroid - t.fine().centroid) < 0.02
    np.testing.assert_allclose(residual, P.forward(surfaces) - data, atol=2e-5)
    # two of them stay on their windows, the others held fixed
    kept, _, two = local_refit(P, moved, data, [0, 3], iterations=5, touch=0.05)
    assert not two["joint"] and two["groups"] == 2 and two["pixels"] / two["evaluations"] < 0.5 * two["scan_pixels"]
    assert all(kept[k] is moved[k] for k in (1, 2, 4))
