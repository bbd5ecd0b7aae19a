"""Quality measures of reconstructions.

* :func:`dice_dissimilarity`: DDI = 1 - 2 |X ∩ Y| / (|X| + |Y|) of two binary
  images (the paper's error measure; 0 = identical, 1 = disjoint).
* :func:`shapes_dice_dissimilarity`: the same for two sets of bubbles
  (meshes or polygons), rasterised on a common grid.
* :func:`projection_mse`: mean squared difference of two projection arrays
  (cross-validation on held-out projections).

Rasterisation is :mod:`bubsub.core.projection.masks`'s (the same code that makes the
phantoms' ground truth); :func:`bubble_mask`, :func:`label_image` and
:func:`rasterize` are re-exported here for convenience.
"""

from __future__ import annotations

import numpy as np

from bubsub.core.projection.masks import bubble_mask, label_image, pixel_centres, rasterize

__all__ = [
    "dice_dissimilarity",
    "shapes_dice_dissimilarity",
    "projection_mse",
    "bubble_mask",
    "label_image",
    "rasterize",
    "pixel_centres",
]


def dice_dissimilarity(x, y):
    """Dice dissimilarity index of two binary images.

    Parameters
    ----------
    x, y : ndarray of bool
        Same shape (any number of dimensions).

    Returns
    -------
    float
        ``1 - 2 |x & y| / (|x| + |y|)`` in [0, 1]; 0 if both are empty.

    Raises
    ------
    ValueError
        If an input is not a boolean array or the shapes differ.
    """
    a, b = _bool(x, "x"), _bool(y, "y")
    if a.shape != b.shape:
        raise ValueError(f"x and y must have the same shape, got {a.shape} and {b.shape}")
    total = int(np.count_nonzero(a)) + int(np.count_nonzero(b))
    if total == 0:
        return 0.0
    inter = int(np.count_nonzero(a & b))
    return 1.0 - 2.0 * inter / total


def shapes_dice_dissimilarity(reconstruction, truth, shape, extent):
    """Dice dissimilarity of two sets of bubbles rasterised on one grid.

    Parameters
    ----------
    reconstruction, truth : sequence of Polygon (2D) or Mesh (3D) or SubdivisionSurface
    shape : (rows, cols) or (slices, rows, cols)
    extent : (xmin, xmax, ymin, ymax[, zmin, zmax])
        mm; grid convention of :mod:`bubsub.core.projection.masks`.

    Returns
    -------
    float
    """
    return dice_dissimilarity(bubble_mask(reconstruction, shape, extent), bubble_mask(truth, shape, extent))


def projection_mse(a, b):
    """Mean squared difference of two projection arrays.

    Parameters
    ----------
    a, b : ndarray
        Same shape, e.g. ``(angle, row, col)``.

    Returns
    -------
    float
        ``mean((a - b)**2)`` computed in float64.

    Raises
    ------
    ValueError
        If shapes differ, an array is empty or not numeric, or values are
        not finite.
    """
    x, y = _numeric(a, "a"), _numeric(b, "b")
    if x.shape != y.shape:
        raise ValueError(f"a and b must have the same shape, got {x.shape} and {y.shape}")
    if x.size == 0:
        raise ValueError("a and b are empty")
    d = x - y
    return float(np.mean(d * d))


def _bool(x, name):
    arr = np.asarray(x)
    if arr.dtype != np.bool_:
        raise ValueError(
            f"{name} must be a boolean array, got dtype {arr.dtype} (binarise it first, e.g. {name} > 0)"
        )
    return arr


def _numeric(x, name):
    arr = np.asarray(x)
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"{name} must be a numeric array, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    return arr
