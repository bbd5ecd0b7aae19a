"""Each bubble subdivided by its size on the detector: no finer than the data resolve.

Loop subdivision ``L`` times turns a control mesh into ``4^L`` times as many
flat faces; the projector's cost follows the faces a view holds, not only
the pixels. At a fixed number of levels a foam of small bubbles pays for
faces the detector cannot tell apart: a bubble 30 pixels across at two
levels has faces of about 2 pixels (docs/scale.md measures the cost on
``bubsub bench scale``'s columns).

A flat face of edge ``e`` on a surface of radius ``r`` stands at most
``e^2 / (8 r)`` from it (the sagitta of its chord). :func:`levels_by_size`
gives each bubble the fewest levels, at most the asked ones, whose faces
stand at most :data:`FACET_PIXELS` detector pixels from a sphere of the
bubble's size: data resolved to a pixel do not see the difference, and the
fit moves the control vertices to make up for the rest. With 42 control
vertices one level meets 0.2 pixels up to a radius of about 18 pixels and
two levels up to about 70 (:func:`facet_depth`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["FACET_PIXELS", "pixels_per_mm", "facet_depth", "levels_by_size", "level_counts"]

#: Most a fine face may stand from a sphere of its bubble's size, in detector pixels (:func:`levels_by_size`).
FACET_PIXELS = 0.2


def pixels_per_mm(geometry, points):
    """Detector pixels per mm at each point, the mean over the views (the magnification of cone beams).

    Measured along each view's detector rows (columns in 2D): a step along
    the detector's own direction is seen at its full length.

    Parameters
    ----------
    geometry : ScanGeometry
    points : (m, ndim) float
        mm.

    Returns
    -------
    (m,) float
    """
    p = np.asarray(points, dtype=float).reshape(-1, geometry.ndim)
    n = geometry.ndim
    vec = geometry.vectors
    axis = vec[:, 9:12] if n == 3 else vec[:, 2 * n:3 * n]  # detector v (3D rows), u in 2D
    unit = axis / np.linalg.norm(axis, axis=1, keepdims=True)
    step = 1e-3  # mm: far below any bubble, far above rounding at scan coordinates
    out = np.zeros(len(p))
    for k in range(geometry.n_angles):
        g = geometry[k:k + 1]
        col0, row0, _ = g.detector_coordinates(p)
        col1, row1, _ = g.detector_coordinates(p + step * unit[k])
        moved = (row1 - row0) if n == 3 else (col1 - col0)
        out += np.abs(moved[0]) / step
    return out / geometry.n_angles


def facet_depth(surface, levels, scale):
    """How far a fine face of ``surface`` subdivided ``levels`` times stands from a sphere of its size, pixels.

    ``e^2 / (8 r)``: ``e`` the control mesh's mean edge halved per level, ``r`` the mean distance of the
    control vertices from their centre, both times ``scale`` (pixels per mm).
    """
    v = surface.vertices
    r = float(np.linalg.norm(v - v.mean(axis=0), axis=1).mean()) * scale
    e = surface.control.mean_edge * scale / 2.0 ** levels
    return e * e / (8.0 * max(r, 1e-12))


def levels_by_size(surfaces, geometry, max_levels, tolerance=FACET_PIXELS, least=1):
    """Each bubble with the fewest subdivision levels whose faces stand at most ``tolerance`` pixels from
    a sphere of its size (:func:`facet_depth`), at least ``least`` and at most ``max_levels``.

    Parameters
    ----------
    surfaces : list of SubdivisionSurface
    geometry : ScanGeometry
        Of the data the bubbles are fitted to (its pixels set the scale).
    max_levels : int
        The most levels (``--levels``).
    tolerance : float or None
        Pixels; None or 0: every bubble at ``max_levels``.
    least : int
        The fewest levels (one: a control mesh's own faces are too coarse for a smooth bubble).

    Returns
    -------
    list of SubdivisionSurface
        Each at its levels, with the same mean radius (``SubdivisionSurface.with_levels(..., keep_size=True)``);
        2D bubbles as they are (a polygon's subdivision costs the projector little).
    """
    surfaces = list(surfaces)
    if not surfaces or geometry.ndim != 3:
        return surfaces
    if not tolerance:
        return [s.with_levels(max_levels, keep_size=True) for s in surfaces]
    if not tolerance > 0:
        raise ValueError(f"the facet tolerance must be a number of pixels >= 0, got {tolerance!r}")
    scale = pixels_per_mm(geometry, np.array([s.vertices.mean(axis=0) for s in surfaces]))
    low = min(least, max_levels)
    out = []
    for s, k in zip(surfaces, scale):
        levels = low
        while levels < max_levels and facet_depth(s, levels, k) > tolerance:
            levels += 1
        out.append(s.with_levels(levels, keep_size=True))
    return out


def level_counts(surfaces):
    """Bubbles per subdivision level, ``{"1": n1, "2": n2, ...}`` (report.json's ``subdivision_levels``)."""
    counts = {}
    for s in surfaces:
        counts[str(s.levels)] = counts.get(str(s.levels), 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: int(kv[0])))
