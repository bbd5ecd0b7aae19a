"""A penalty that keeps bubbles apart during the fit: no gas counted twice.

The projection distance alone lets two neighbouring bubbles interpenetrate
(their overlap is counted twice, which at few views the fit trades against
gas missing elsewhere). For each pair ``(i, j)`` of bubbles whose bounding
balls come within ``gap`` of each other, with ``n`` the unit vector between
their control centroids, ``a_k = x_ik . n`` (control vertices of ``i``) and
``b_l = x_jl . n`` (of ``j``), the penalty is

    P_ij = 0.5 w min_t [ sum_k relu(a_k - t + gap/2)^2 + sum_l relu(t + gap/2 - b_l)^2 ]

the squared distance the control vertices would have to move along ``n`` so
that a plane (offset ``t``) separates them with ``gap`` between. It is zero
when they are separated, continuous and differentiable (``t`` minimises a
convex function, so by Danskin's theorem the gradient is that of the
bracket at the best ``t``, plus the terms through ``n``). Loop and cubic
B-spline subdivision are convex combinations of the control vertices, so
separated control vertices mean separated fine surfaces with at least
``gap`` between: a liquid film of at least that thickness is kept.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["separation_penalty", "separation_weight"]


def _best_offset(a, b, half_gap, steps=60):
    """The ``t`` minimising the bracket (its derivative in ``t`` is increasing): bisection."""
    lo, hi = float(b.min()) - half_gap, float(a.max()) + half_gap
    for _ in range(steps):
        t = 0.5 * (lo + hi)
        slope = -np.sum(np.maximum(a - t + half_gap, 0.0)) + np.sum(np.maximum(t + half_gap - b, 0.0))
        if slope > 0:
            hi = t
        else:
            lo = t
    return 0.5 * (lo + hi)


def candidate_pairs(vertex_sets, gap):
    """Pairs ``(i, j)``, ``i < j``, whose bounding balls (control centroid, farthest control vertex) come within ``gap``."""
    centres = np.array([v.mean(axis=0) for v in vertex_sets])
    radii = np.array([np.linalg.norm(v - c, axis=1).max() for v, c in zip(vertex_sets, centres)])
    if len(centres) < 2:
        return []
    pairs = cKDTree(centres).query_pairs(2 * float(radii.max()) + gap)
    return sorted((i, j) for i, j in pairs if np.linalg.norm(centres[i] - centres[j]) < radii[i] + radii[j] + gap)


def separation_penalty(vertex_sets, weight, gap=0.0):
    """Penalty for interpenetrating bubbles and its gradient.

    Parameters
    ----------
    vertex_sets : list of (n_k, ndim) float
        Control vertices of each bubble, mm.
    weight : float
        ``w``, objective units per mm^2.
    gap : float
        Least film between two bubbles, mm.

    Returns
    -------
    value : float
    grads : list of (n_k, ndim) float
        d value / d vertices, per bubble.
    """
    grads = [np.zeros_like(v, dtype=float) for v in vertex_sets]
    value = 0.0
    h = 0.5 * gap
    for i, j in candidate_pairs(vertex_sets, gap):
        vi, vj = vertex_sets[i], vertex_sets[j]
        d = vj.mean(axis=0) - vi.mean(axis=0)
        dist = float(np.linalg.norm(d))
        if dist == 0:
            continue  # concentric bubbles: no direction; the validity check reports them
        n = d / dist
        a, b = vi @ n, vj @ n
        if a.max() + h <= b.min() - h:
            continue
        t = _best_offset(a, b, h)
        pa = np.maximum(a - t + h, 0.0)  # how far each vertex of i is beyond the plane
        pb = np.maximum(t + h - b, 0.0)
        value += 0.5 * weight * float(pa @ pa + pb @ pb)
        # through a and b with n fixed
        grads[i] += weight * pa[:, None] * n
        grads[j] -= weight * pb[:, None] * n
        # through n = d / |d|, d = mean(vj) - mean(vi)
        dn = weight * (pa @ vi - pb @ vj)
        dd = (dn - n * float(n @ dn)) / dist
        grads[j] += dd / len(vj)
        grads[i] -= dd / len(vi)
    return value, grads


def separation_weight(data, n_bubbles, voxel, strength=1.0):
    """``w`` such that an overlap of one voxel costs about ``strength / 2`` x a typical bubble's share of the data.

    A bubble's share is ``0.5 ||d||^2 / n_bubbles`` (the objective of leaving
    it out, roughly); at ``strength = 1`` overlaps well below a voxel are
    cheap and a voxel's overlap is as costly as half a missing bubble.
    """
    d = np.asarray(data, dtype=np.float64).ravel()
    return float(strength * 0.5 * float(d @ d) / max(n_bubbles, 1) / voxel**2)
