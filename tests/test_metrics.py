"""Dice dissimilarity and projection MSE against hand-computed and analytic values."""

import numpy as np
import pytest

from bubsub.core.projection.mesh import Polygon
from bubsub.core.metrics import bubble_mask, dice_dissimilarity, projection_mse, shapes_dice_dissimilarity
from bubsub.core.foam.containers import sphere_mesh
from bubsub.core.foam.phantoms import foam3d_benchmark


def disk(centre, r, n=1024):
    t = 2 * np.pi * np.arange(n) / n
    return Polygon(np.c_[centre[0] + r * np.cos(t), centre[1] + r * np.sin(t)], -0.1)


def test_dice_hand_computed():
    x = np.zeros((4, 4), bool)
    y = np.zeros((4, 4), bool)
    x[0, :4] = True  # 4 pixels
    y[0, 2:] = True
    y[1, :2] = True  # 4 pixels, 2 shared
    assert dice_dissimilarity(x, y) == pytest.approx(1 - 2 * 2 / 8)
    assert dice_dissimilarity(y, x) == dice_dissimilarity(x, y)
    assert dice_dissimilarity(x, x) == 0.0
    assert dice_dissimilarity(x, ~x) == 1.0
    assert dice_dissimilarity(np.zeros(5, bool), np.zeros(5, bool)) == 0.0
    assert dice_dissimilarity(np.zeros(5, bool), np.ones(5, bool)) == 1.0


def test_dice_bad_input():
    with pytest.raises(ValueError, match=r"same shape, got \(3,\) and \(4,\)"):
        dice_dissimilarity(np.zeros(3, bool), np.zeros(4, bool))
    with pytest.raises(ValueError, match="x must be a boolean array, got dtype int64"):
        dice_dissimilarity(np.zeros(3, np.int64), np.zeros(3, bool))
    with pytest.raises(ValueError, match="y must be a boolean array"):
        dice_dissimilarity(np.zeros(3, bool), np.zeros(3))


def test_shapes_dice_of_two_offset_disks_matches_the_lens_area():
    r, d = 1.0, 0.6
    lens = 2 * r * r * np.arccos(d / (2 * r)) - d / 2 * np.sqrt(4 * r * r - d * d)
    expected = 1 - lens / (np.pi * r * r)
    got = shapes_dice_dissimilarity([disk((0.0, 0.0), r)], [disk((d, 0.0), r)], (800, 800), (-2, 2, -2, 2))
    assert got == pytest.approx(expected, abs=2e-3)
    assert shapes_dice_dissimilarity([disk((0.1, 0.2), r)], [disk((0.1, 0.2), r)], (200, 200), (-2, 2, -2, 2)) == 0


def test_shapes_dice_in_3d_for_a_slightly_grown_sphere():
    # DDI of concentric balls r and R: 1 - 2 r^3 / (r^3 + R^3)
    a, b = sphere_mesh((0, 0, 0), 1.0, 1.0, subdivisions=4), sphere_mesh((0, 0, 0), 1.1, 1.0, subdivisions=4)
    got = shapes_dice_dissimilarity([a], [b], (80, 80, 80), (-1.2, 1.2, -1.2, 1.2, -1.2, 1.2))
    assert got == pytest.approx(1 - 2 * 1.0 / (1.0 + 1.1**3), abs=4e-3)


def test_benchmark_against_itself_and_a_shifted_copy():
    scene = foam3d_benchmark()
    grid = ((50, 100, 100), (-10, 10, -10, 10, -5, 5))
    assert shapes_dice_dissimilarity(scene.bubbles, scene.bubbles, *grid) == 0.0
    shifted = [m.with_vertices(m.vertices + [0.2, 0, 0]) for m in scene.bubbles]
    ddi = shapes_dice_dissimilarity(shifted, scene.bubbles, *grid)
    assert 0.05 < ddi < 0.3
    assert bubble_mask(scene.bubbles, *grid).sum() > 0


def test_projection_mse():
    a = np.zeros((2, 3, 4), np.float32)
    b = np.full((2, 3, 4), 0.5)
    assert projection_mse(a, b) == pytest.approx(0.25)
    assert projection_mse(b, b) == 0.0
    with pytest.raises(ValueError, match="same shape"):
        projection_mse(a, b[:1])
    with pytest.raises(ValueError, match="b contains NaN"):
        projection_mse(a, np.full(a.shape, np.nan))
    with pytest.raises(ValueError, match="empty"):
        projection_mse(np.zeros(0), np.zeros(0))
    with pytest.raises(ValueError, match="numeric"):
        projection_mse(np.array(["a"]), np.array(["b"]))
