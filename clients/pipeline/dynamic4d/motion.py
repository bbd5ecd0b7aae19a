"""Each track's last step (displacement and growth), measured at its warm fit, the warm start it predicts, and the
foam's flow during a subscan.

A flowing foam carries its bubbles a few pixels per subscan, and a
coarsening or expanding one changes their sizes. A warm start that is the
successor's bubble shrunk in place leaves the fit to find both; the steps
the tracks took between the successor and its own successor predict them:
the foam's motion is smooth in space and time. :func:`measure_steps`
records, after a warm fit, each bubble's displacement and radius ratio
against its successor (bubbles wholly in view only: a cut bubble's centroid
lies toward its unseen part); :func:`predict` gives each bubble of the next
warm start the median displacement of its nearest measured neighbours and
its own radius ratio (else theirs). On the flowing foam of ``bubsub bench
dynamic`` this lowers a warm fit's initial objective five to six times and
its median iterations from 65 to 57.

The foam also moves while a subscan is acquired. :func:`flow_during` spreads
the tracks' median step over the subscan's projections, and
:func:`flow_in_data` measures the flow along the rotation axis from the
data's row sums where no step is known; the chain fits each subscan in that
frame (``ScanGeometry.moved``).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from bubsub.clients.pipeline.inputs.fov import field_of_view, reaches_edge_rows, sides_clear

__all__ = ["STEP_NEIGHBOURS", "MIN_STEPS", "START_MARGIN", "measure_steps", "predict", "flow_during",
           "flow_in_data"]

#: Measured bubbles whose displacements give a bubble's predicted one (its nearest, itself included).
STEP_NEIGHBOURS = 8

#: Fewer measured neighbours than this predict nothing (the start is the successor's bubble shrunk in place).
MIN_STEPS = 3

#: A predicted start is this fraction of the predicted size, so that it starts inside its bubble, as the
#: shrink of an unpredicted start does (it then grows into its gas rather than into its neighbours).
START_MARGIN = 0.95


def _in_view(surface, half):
    """Whether a bubble lies between the detector's top and bottom planes (always in 2D: ``half`` None)."""
    return half is None or not reaches_edge_rows(surface.fine().vertices, half)


def _centroid_radius(surface):
    fine = surface.fine()
    return np.asarray(fine.centroid, dtype=float), float(fine.equivalent_radius)


def measure_steps(previous_ids, previous_surfaces, ids, surfaces, geometry):
    """Each bubble's step from its successor's bubble: displacement and radius ratio.

    Parameters
    ----------
    previous_ids : sequence of int
        The successor's track ids.
    previous_surfaces : sequence of SubdivisionSurface
        The successor's bubbles, in ``previous_ids`` order.
    ids : sequence of int
        This subscan's track ids.
    surfaces : sequence of SubdivisionSurface
        This subscan's fitted bubbles, in ``ids`` order.
    geometry : ScanGeometry
        This subscan's (its field of view decides which bubbles are wholly in view).

    Returns
    -------
    tuple
        One entry per bubble of ``ids``: ``(d_1, ..., d_ndim, ratio)`` (mm,
        then the equivalent radius over the successor's), or None for a bubble
        new here or cut by the detector's top or bottom plane, here or in the
        successor.
    """
    half = field_of_view(geometry)[1] if geometry.ndim == 3 else None
    before = {int(i): s for i, s in zip(previous_ids, previous_surfaces)}
    out = []
    for i, s in zip(ids, surfaces):
        p = before.get(int(i))
        if p is None or not (_in_view(s, half) and _in_view(p, half)):
            out.append(None)
            continue
        (c, r), (c0, r0) = _centroid_radius(s), _centroid_radius(p)
        out.append(tuple(float(x) for x in c - c0) + (r / r0,) if r0 > 0 else None)
    return tuple(out)


def predict(surfaces, steps):
    """The predicted displacement and radius ratio of each bubble of the next warm start.

    Parameters
    ----------
    surfaces : sequence of SubdivisionSurface
        The bubbles the next warm start is built from.
    steps : tuple
        :func:`measure_steps` of these bubbles (empty: none known).

    Returns
    -------
    shifts : (n, ndim) float
        mm; zero where fewer than :data:`MIN_STEPS` measured bubbles are near.
    ratios : (n,) float
        The bubble's own measured radius ratio, else its measured neighbours'
        median; NaN where none is known.
    """
    n = len(surfaces)
    ndim = surfaces[0].ndim if n else 3
    shifts, ratios = np.zeros((n, ndim)), np.full(n, np.nan)
    if len(steps) != n:
        return shifts, ratios
    known = [k for k, s in enumerate(steps) if s is not None]
    if len(known) < MIN_STEPS:
        return shifts, ratios
    centres = np.array([_centroid_radius(s)[0] for s in surfaces])
    measured = np.array([steps[k] for k in known], dtype=float)
    _, near = cKDTree(centres[known]).query(centres, k=min(STEP_NEIGHBOURS, len(known)))
    shifts = np.median(measured[near, :ndim], axis=1)
    ratios = np.median(measured[near, ndim], axis=1)
    for k in known:
        ratios[k] = steps[k][ndim]
    return shifts, ratios


def flow_during(steps, n_views, times=None, ndim=3):
    """The foam's displacement at each projection of a subscan from its position at the subscan's mid-time.

    A flowing foam moves between projections (on the flowing foam of ``bubsub bench dynamic``, 4 pixels over a
    subscan of 40), and a fit of bubbles standing still spreads a thin cap at the detector's edge over the rows
    it crossed. Its tracks' steps give the flow: the median of :func:`measure_steps`' displacements (the subscan
    after this one's bubbles, measured at its warm fit: going backwards in time, so the foam moves by minus it
    over a subscan forward), taken as uniform in space and steady over the subscan, which lasts from its first
    projection to one projection interval past its last (subscans acquired back to back).

    Parameters
    ----------
    steps : tuple
        :func:`measure_steps` of the subscan after this one (empty: none known).
    n_views : int
        This subscan's projections.
    times : (n_views,) float, optional
        Their acquisition times (any unit); evenly spaced when None.
    ndim : int

    Returns
    -------
    (n_views, ndim) float or None
        mm; None where fewer than :data:`MIN_STEPS` bubbles were measured.
    """
    measured = [st[:ndim] for st in steps if st is not None]
    if len(measured) < MIN_STEPS or n_views < 2:
        return None
    step = np.median(np.asarray(measured, dtype=float), axis=0)
    fraction = _fractions(n_views, times)
    return None if fraction is None else -fraction[:, None] * step[None, :]


def _fractions(n_views, times):
    """(n_views,) float: each projection's time from the subscan's mid-time, in subscans (one lasts from its
    first projection to one projection interval past its last); None when the times do not advance."""
    t = np.arange(n_views, dtype=float) if times is None else np.asarray(times, dtype=float)
    span = (t.max() - t.min()) * n_views / (n_views - 1)
    return (t - 0.5 * (t.min() + t.max())) / span if span > 0 else None


def flow_in_data(data, geometry, contrast, times=None):
    """The foam's displacement along the rotation axis at each projection from its position at the mid-time,
    measured in the data: for a subscan whose tracks measured no steps (the cold start, the warm subscan after it).

    In a parallel beam each projection's row sums are the sample's bubble signal integrated over a slice,
    whatever the angle, so a foam that flows along the axis shifts them between projections and nothing else
    does. Each projection's shift against the mean profile (Gauss-Newton on the profile's gradient, three
    passes) is fitted by a line in the projections' times; its slope is the flow, taken as steady over the
    subscan (:func:`flow_during`'s convention). The flow across the axis does not show in the row sums and is
    not measured.

    Parameters
    ----------
    data : ndarray, ``(views, rows, cols)``
        The bubbles' signal (``data - background``).
    geometry : ScanGeometry
    contrast : float
        Bubble contrast.
    times : (views,) float, optional
        The projections' acquisition times; evenly spaced when None.

    Returns
    -------
    (views, 3) float or None
        mm; None for a cone beam or 2D scan, fewer than 4 projections, bubble signal at a side of the detector
        (a part of the sample out of view changes the row sums with the angle), or a profile without structure.
    """
    if geometry.ndim != 3 or geometry.is_cone or data.shape[0] < 4 or not sides_clear(data, contrast):
        return None
    profile = np.sign(contrast) * np.asarray(data, dtype=np.float64).sum(axis=2)  # (views, rows)
    n_views, n_rows = profile.shape
    rows = np.arange(n_rows, dtype=float)
    shifts = np.zeros(n_views)
    for _ in range(3):
        # each profile moved back by its shift, their mean the reference
        aligned = np.array([np.interp(rows + s, rows, p) for s, p in zip(shifts, profile)])
        mean = aligned.mean(axis=0)
        grad = np.gradient(mean)
        inner = slice(4, n_rows - 4)  # rows a shift of a few pixels keeps inside the detector
        g = grad[inner]
        if not np.dot(g, g) > 0:
            return None
        shifts += np.array([np.dot(mean[inner] - a[inner], g) for a in aligned]) / np.dot(g, g)
    fraction = _fractions(n_views, times)
    if fraction is None:
        return None
    rows_per_subscan = np.polyfit(fraction, shifts, 1)[0]
    row_vectors = geometry.vectors[:, 9:12]
    return fraction[:, None] * rows_per_subscan * row_vectors
