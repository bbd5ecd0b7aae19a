"""Track ids in a warm subscan: which bubble continues which, coalescences seen backwards, tracks that end.

After a warm subscan's detection (:mod:`bubsub.clients.pipeline.dynamic4d.detect`)
:func:`assign_tracks` gives every bubble its track: a bubble that lies
mostly inside one fitted bubble continues its id; a fitted bubble that became
two is a coalescence (forward in time) when the two look like one
(:func:`coalesces`: both wholly in the field of view, of comparable size,
together nearer the successor's bubble's size than the larger alone), both
with new ids and the lineage ``children -> parent``; otherwise (one of the two
is the bubble, the other a bubble whose space its warm fit took, or a cap
beside a neighbour cut by the same detector edge) the larger keeps the id.
Bubbles inside none are new tracks. Ids come from ``next_id`` upward and are
never reused in a run.
"""

from __future__ import annotations

import numpy as np

from bubsub.core.projection.masks import coverage
from bubsub.clients.pipeline.inputs.fov import field_of_view, fov_report, reaches_edge_rows, truncated_flags

__all__ = ["CONTINUES", "COALESCENCE_SHARE", "assign_tracks", "coalesces", "overlap_fraction", "edge_side",
           "size_of", "centre_of", "reach_of"]

#: A bubble after the rounds continues the fitted bubble that holds at least this fraction of it.
CONTINUES = 0.5

#: A bubble after the rounds that one fitted bubble holds this much of continues it without more measures.
SURELY = 0.75

#: A coalescence's smaller child holds at least this share of the two children's size (in 3D 0.56 times the
#: other's radius, in 2D 0.42): a cap or a sliver beside a neighbour is not the other half of a coalescence.
COALESCENCE_SHARE = 0.15

#: Cells along the longest side of the grid on which two bubbles' overlap is measured.
OVERLAP_CELLS = 20


def overlap_fraction(item, other, cells=OVERLAP_CELLS):
    """Fraction of ``item``'s area (volume) inside ``other``, rasterised on a grid over ``item``'s box.

    Parameters
    ----------
    item, other : SubdivisionSurface, Mesh or Polygon
    cells : int
        Grid cells along the box's longest side (two sub-samples per cell and axis).

    Returns
    -------
    float
        In [0, 1].
    """
    a, b = item.fine() if hasattr(item, "fine") else item, other.fine() if hasattr(other, "fine") else other
    v = np.asarray(a.vertices, dtype=float)
    lo, hi = v.min(axis=0), v.max(axis=0)
    ov, oh = np.asarray(b.vertices).min(axis=0), np.asarray(b.vertices).max(axis=0)
    if np.any(oh < lo) or np.any(ov > hi):
        return 0.0
    h = float((hi - lo).max()) / cells
    ndim = v.shape[1]
    shape = tuple(max(1, int(np.ceil((hi[k] - lo[k]) / h))) for k in reversed(range(ndim)))
    extent = tuple(x for k in range(ndim) for x in (lo[k], lo[k] + shape[ndim - 1 - k] * h))
    fa = coverage(a, shape, extent, supersample=2)
    total = float(fa.sum())
    if total <= 0:
        return 0.0
    return float(np.minimum(fa, coverage(b, shape, extent, supersample=2)).sum()) / total


def edge_side(surface, geometry):
    """Where a bubble meets the edge of the field of view: ``"top"`` (z > 0 in 3D), ``"bottom"``, ``"side"``
    (the cylinder, or the disc in 2D) or None."""
    fov = field_of_view(geometry)
    fine = surface.fine()
    if not truncated_flags([fine], fov, fov_report(geometry)["margin"])[0]:
        return None
    v = np.asarray(fine.vertices)
    if reaches_edge_rows(v, fov[1], fov_report(geometry)["margin"]):
        return "top" if float(np.mean(v[:, 2])) > 0 else "bottom"
    return "side"


def size_of(surface):
    """Area (2D, mm^2) or volume (3D, mm^3) of a bubble's smooth surface (its mesh's ``size``, unsigned)."""
    return abs(float(surface.fine().size))


def centre_of(surface):
    """Centroid of a bubble's smooth surface, ``(ndim,)`` mm."""
    return np.asarray(surface.fine().centroid, dtype=float)


def reach_of(surface):
    """Largest distance of a smooth-surface vertex from the vertices' mean, mm."""
    v = surface.fine().vertices
    return float(np.linalg.norm(v - v.mean(axis=0), axis=1).max())


def _parents(before, after):
    """For each bubble of ``after``: the index of the ``before`` bubble it continues, or -1.

    The same object continues itself; another continues the nearby ``before`` bubble holding at least
    :data:`CONTINUES` of it, the most. The nearest are measured first, and one holding :data:`SURELY` of it ends the
    search: the warm fit's bubbles overlap little, so no other holds as much (a warm subscan's refits leave half
    its bubbles new objects, each measured against every bubble near it otherwise: 2 s of the subscan).
    """
    same = {id(s): k for k, s in enumerate(before)}
    centres = np.array([centre_of(s) for s in before]) if before else np.zeros((0, 1))
    radii = np.array([reach_of(s) for s in before])
    out = []
    for s in after:
        if id(s) in same:
            out.append(same[id(s)])
            continue
        c, r = centre_of(s), reach_of(s)
        d = np.linalg.norm(centres - c, axis=1) if len(before) else np.zeros(0)
        near = np.nonzero(d <= radii + r)[0]
        best, frac = -1, CONTINUES
        for k in near[np.argsort(d[near], kind="stable")]:
            f = overlap_fraction(s, before[k])
            if f >= frac:
                best, frac = int(k), f
            if frac >= SURELY:
                break
        out.append(best)
    return out


def coalesces(sizes, sides, known):
    """Whether a fitted bubble that became two is one bubble in the successor too: a coalescence forward in time.

    A coalescence as the chain sees it going backwards: two bubbles of comparable size, each a real share of
    the pair (:data:`COALESCENCE_SHARE`), both wholly in the field of view, that together hold about the
    successor's bubble's size (nearer it than the larger alone). Otherwise the larger continues the track and
    the other is a bubble the warm fit covered: a cap that leaves through the detector's edge later beside a
    neighbour cut by the same edge (the visible parts' sizes say nothing of the bubbles'), or a small bubble
    beside a neighbour that swelled into its space in the successor.

    Parameters
    ----------
    sizes : sequence of float
        The children's areas (2D) or volumes (3D), largest first, at least two.
    sides : sequence of str or None
        :func:`edge_side` of each child.
    known : float or None
        The size of the successor's bubble (None: unknown, never a coalescence).

    Returns
    -------
    bool
    """
    if known is None or len(sizes) < 2:
        return False
    big, small = float(sizes[0]), float(sizes[1])
    return (sides[0] is None and sides[1] is None and small >= COALESCENCE_SHARE * (big + small)
            and abs(known - big - small) < abs(known - big))


def assign_tracks(ids, before, after, successor_sizes, geometry, next_id):
    """Track ids of the bubbles after the warm subscan's topology rounds, and the lineage they imply.

    A bubble of ``after`` lying mostly (:data:`CONTINUES`) inside one of ``before`` continues it. A fitted
    bubble that became two or more: its two largest children are a coalescence forward in time when
    :func:`coalesces` says so (both take new ids, the lineage ``children -> parent``); otherwise the largest
    keeps the id. Every other child is a new track, split off the fitted bubble.

    Parameters
    ----------
    ids : sequence of int
        Track ids of ``before``.
    before : list of SubdivisionSurface
        The warm fit's bubbles.
    after : list of SubdivisionSurface
        The bubbles after :func:`detect_warm`'s rounds.
    successor_sizes : dict
        ``id -> area (2D) or volume (3D)`` of each track's bubble in the successor subscan (mm^2 or mm^3).
    geometry : ScanGeometry
        Of the fitted projections (the field of view, for the reasons).
    next_id : int
        The first unused track id.

    Returns
    -------
    new_ids : list of int
        One per ``after`` bubble.
    lineage : dict
        ``new`` (``{id: reason}``: tracks that start here going backwards, i.e. end here forward in time),
        ``coalescences`` (``[{"parent": id, "children": [id, id]}]``: one bubble in the successor, two here),
        ``removed`` (``{id: reason}``: tracks the rounds removed).
    next_id : int
        The first id still unused.
    """
    parents = _parents(before, after)
    children = {}
    for j, k in enumerate(parents):
        if k >= 0:
            children.setdefault(k, []).append(j)
    new_ids = [None] * len(after)
    lineage = {"new": {}, "coalescences": [], "removed": {}}

    def fresh():
        nonlocal next_id
        next_id += 1
        return next_id - 1

    for k, js in children.items():
        if len(js) == 1:
            new_ids[js[0]] = int(ids[k])
            continue
        sizes = [size_of(after[j]) for j in js]
        js = [js[i] for i in np.argsort(sizes)[::-1]]
        sizes = sorted(sizes, reverse=True)
        sides = [edge_side(after[j], geometry) for j in js]
        if coalesces(sizes, sides, successor_sizes.get(int(ids[k]))):
            got = [fresh() for _ in js[:2]]
            for j, i in zip(js, got):
                new_ids[j] = i
            lineage["coalescences"].append({"parent": int(ids[k]), "children": got})
            rest = 2
        else:
            new_ids[js[0]] = int(ids[k])
            rest = 1
        for j, side in zip(js[rest:], sides[rest:]):
            new_ids[j] = fresh()
            lineage["new"][new_ids[j]] = (f"split off bubble {int(ids[k])}, whose warm fit covered it"
                                          + (f", at the {side} edge of the field of view" if side else ""))
    for j, s in enumerate(after):
        if new_ids[j] is None:
            new_ids[j] = fresh()
            side = edge_side(s, geometry)
            lineage["new"][new_ids[j]] = (f"at the {side} edge of the field of view" if side else
                                          "inside the field of view, without a warm start")
    for k, i in enumerate(ids):
        if k not in children:
            side = edge_side(before[k], geometry)
            lineage["removed"][int(i)] = (f"left the field of view (a sliver at its {side} edge, removed by the "
                                          f"topology rounds)" if side else
                                          "collapsed (removed by the topology rounds: it explains less than its "
                                          "unknowns cost)")
    return new_ids, lineage, next_id
