"""Whether a coalescence that a warm subscan's detection splits had already happened at the subscan's mid-time.

A subscan stands for the foam at its mid-time, but its projections are taken over a whole half turn (a turn in cone
beam) while the foam changes. Going backwards, a pair that coalesces during subscan ``k`` is one bubble in the
successor ``k + 1``; subscan ``k``'s detection sees the pair in the projections taken before the film broke and
splits the bubble in two when that lowers the objective enough, which it does even when the film broke early in the
subscan (on the second seed of ``bubsub bench dynamic``'s flowing foam: 27 % and 41 % of the way through, so one
bubble at mid-time, and the lineage a subscan late).

:func:`merged_at_midtime` reads the time out of the data. For each view ``v`` (acquisition order) the split's gain
``g_v = 0.5 (||r_one,v||^2 - ||r_two,v||^2)`` compares the scene with the warm fit's one bubble and with the two.
Over a subscan's full period of angles its first and last views see the same lines (180 degrees apart in parallel
beam, 360 in cone beam), so for a foam that does not change, ``g`` joins up across the ends like its neighbouring
views do, whatever it does in between. A film that breaks during the subscan makes it jump there:
:func:`midtime_drop`, ``(mean g[:m] - mean g[-m:]) / median |g_v - g_(v-1)|``, measures that jump against the
gain's own view-to-view change, and :func:`event_view` places the break, the view that best cuts ``g`` into two
levels. The split is undone when the jump is clear (:data:`MIDTIME_DROP`), the break lies in the subscan's first
half and the two bubbles' gain falls across it to a small share of what it was (:data:`AFTER_SHARE`).

Measured on the flowing foam's seeds 0 and 1 (``bubsub bench dynamic``; the break's place from the simulation's
events.csv): for films broken 27 %, 41 %, 79 % and 90 % of the way through a subscan the jumps are 14.6, 9.5, -8.9
and -7.2, placed at 23 %, 83 %, 80 % and 90 %; one broken at 35 % gives 3.5 (placed at 35 %), one at 90 % with no
jump in its gain 2.7, and pairs whose film lasts the whole subscan -0.9 and 3.2. So the rule undoes the 27 % split
only: a wrong call merges a pair, a missed one records a coalescence a subscan late, so the threshold stays above
what films that last the whole subscan give.

Only a subscan whose views span a full period is read this way (:func:`spans_a_period`).

A bubble that shrinks to nothing early in the subscan is the simpler case (:func:`absent_at_midtime`): going
backwards it is new there, seen by the views taken before it vanished and found, a bubble that the subscan's
mid-time does not hold (on the second seed of the flowing foam, one that vanished 43 % of the way through
subscan 1). Its support per view (the objective's rise were it removed) is positive in the views that see it and
negative in the others, where the fitted bubble stands in data that hold none; whether most of the subscan's middle
third support it (the median's sign) says whether it is there at mid-time (a sum would let a few views that see the
whole bubble outweigh more that see none of the smaller one fitted). Only new bubbles wholly in the field of view are
tested: a cap at the detector's top or bottom edge moves through the edge plane all through the subscan, and on the
flowing foam's first seed the test took caps one or two rows deep that the mid-time holds.
"""

from __future__ import annotations

import numpy as np

from bubsub.core.io.scan import theta_from_geometry

from bubsub.clients.pipeline.regions.local import footprint
from bubsub.clients.pipeline.dynamic4d.tracks import edge_side

__all__ = ["ENDS", "MIDTIME_DROP", "AFTER_SHARE", "spans_a_period", "view_gains", "midtime_drop", "event_view",
           "merged_at_midtime", "middle_views", "absent_at_midtime"]

#: Views averaged at each end of the subscan by :func:`midtime_drop`.
ENDS = 3

#: Least :func:`midtime_drop` at which a coalescence's split is undone (the pair is one bubble at mid-time).
MIDTIME_DROP = 5.0

#: The most the split's mean gain after the break may be, as a share of its mean gain before it, for the split to
#: be undone: the one bubble explains the views after the break about as well as the two (on the flowing foam,
#: 0.08 where the film broke 27 % of the way through a subscan; 0.33 for a film that lasts the whole subscan).
AFTER_SHARE = 0.25


def spans_a_period(geometry):
    """Whether the views span one period of directions (180 degrees in parallel beam, 360 in cone beam) to within
    half a view's step, so that the first view and the one after the last see the same lines."""
    theta = theta_from_geometry(geometry)
    if len(theta) < 4 * ENDS:
        return False
    step = float(np.median(np.abs(np.diff(theta))))
    period = 360.0 if geometry.is_cone else 180.0
    return abs(abs(float(theta[-1] - theta[0])) + step - period) <= 0.5 * step


def view_gains(projector, residual, one, two):
    """Per view, how much better two bubbles explain the data than one: ``0.5 (||r_one||^2 - ||r_two||^2)``.

    Parameters
    ----------
    projector : MeshProjector
    residual : ndarray float64, ``projector.geometry.shape``
        ``Proj(scene) - data`` of the scene holding ``two``.
    one : SubdivisionSurface
    two : list of SubdivisionSurface

    Returns
    -------
    (n_views,) float
    """
    r_two = np.asarray(residual, dtype=np.float64)
    r_one = r_two + np.asarray(projector.forward([one]), dtype=np.float64) \
        - np.asarray(projector.forward(list(two)), dtype=np.float64)
    n = len(r_two)
    return 0.5 * (np.einsum("ij,ij->i", r_one.reshape(n, -1), r_one.reshape(n, -1))
                  - np.einsum("ij,ij->i", r_two.reshape(n, -1), r_two.reshape(n, -1)))


def midtime_drop(gains):
    """The fall of a split's per-view gain from the subscan's first :data:`ENDS` views to its last, over the gain's
    median change from one view to the next (0 where the gain does not change).

    Parameters
    ----------
    gains : (n,) float
        :func:`view_gains`, in acquisition order.

    Returns
    -------
    float
    """
    g = np.asarray(gains, dtype=float)
    step = float(np.median(np.abs(np.diff(g)))) if len(g) > 1 else 0.0
    jump = float(g[:ENDS].mean() - g[-ENDS:].mean())
    if step <= 0:
        return 0.0 if jump == 0 else np.sign(jump) * np.inf
    return jump / step


def event_view(gains):
    """Where a split's per-view gain changes level: the view ``s`` (at least :data:`ENDS` from either end) that
    best cuts ``gains`` into two constant parts, and the two parts' means.

    Parameters
    ----------
    gains : (n,) float
        :func:`view_gains`, in acquisition order (``n >= 2 ENDS``).

    Returns
    -------
    s : int
        The first view after the change.
    before, after : float
        Mean gain of views ``[0, s)`` and ``[s, n)``.
    """
    g = np.asarray(gains, dtype=float)
    n = len(g)
    s = np.arange(ENDS, n - ENDS + 1)
    head = np.cumsum(g)[s - 1]
    # the two-level fit's squared error is sum(g^2) - head^2 / s - tail^2 / (n - s): maximise the explained part
    tail = g.sum() - head
    best = int(s[np.argmax(head ** 2 / s + tail ** 2 / (n - s))])
    return best, float(g[:best].mean()), float(g[best:].mean())


def merged_at_midtime(projector, residual, ids, before, new_ids, after, lineage):
    """Undo the coalescences (splits going backwards) whose pair was already one bubble at the subscan's mid-time.

    Parameters
    ----------
    projector : MeshProjector
        Of the subscan's bubble signal, views in acquisition order.
    residual : ndarray float64, ``projector.geometry.shape``
        ``Proj(after) - data`` (:func:`~bubsub.clients.pipeline.regions.local.scene_residual`); updated in place
        for the pairs undone.
    ids : sequence of int
        Track ids of ``before``.
    before : list of SubdivisionSurface
        The warm fit (each coalescence's parent is one of them).
    new_ids : list of int
    after : list of SubdivisionSurface
        The bubbles after the detection, with their track ids.
    lineage : dict
        :func:`~bubsub.clients.pipeline.dynamic4d.tracks.assign_tracks`'s.

    Returns
    -------
    new_ids, after : list
        With each undone pair's two bubbles replaced by the parent's warm fit under the parent's id (at the end).
    lineage : dict
        Without the undone coalescences.
    undone : list of dict
        ``{"parent", "children", "drop", "view"}`` per undone coalescence.
    """
    if not lineage["coalescences"] or not spans_a_period(projector.geometry):
        return new_ids, after, lineage, []
    warm = {int(i): s for i, s in zip(ids, before)}
    index, undone, kept = {int(i): k for k, i in enumerate(new_ids)}, [], []
    for c in lineage["coalescences"]:
        one = warm[int(c["parent"])]
        two = [after[index[int(i)]] for i in c["children"]]
        gains = view_gains(projector, residual, one, two)
        drop = midtime_drop(gains)
        view, higher, lower = event_view(gains)
        if drop >= MIDTIME_DROP and view < len(gains) / 2 and 0 < higher and lower <= AFTER_SHARE * higher:
            undone.append({"parent": int(c["parent"]), "children": [int(i) for i in c["children"]], "drop": drop,
                           "view": view})
        else:
            kept.append(c)
    if not undone:
        return new_ids, after, lineage, []
    gone = {i for u in undone for i in u["children"]}
    for i in gone:
        footprint(projector, after[index[i]]).add_to(residual, -1.0)
    parents = [u["parent"] for u in undone]
    for p in parents:
        footprint(projector, warm[p]).add_to(residual)
    keep = [k for k, i in enumerate(new_ids) if int(i) not in gone]
    new_ids = [new_ids[k] for k in keep] + parents
    after = [after[k] for k in keep] + [warm[p] for p in parents]
    return new_ids, after, dict(lineage, coalescences=kept), undone


def middle_views(n):
    """The views that stand for a subscan of ``n`` views at its mid-time: its middle third, a slice."""
    third = n // 3
    return slice(third, n - third)


def absent_at_midtime(projector, residual, ids, new_ids, after, lineage):
    """The new bubbles that only views away from the subscan's mid-time see, taken out.

    Tested: each bubble new in the subscan and wholly in the field of view (coalescences' halves left to
    :func:`merged_at_midtime`; caps at the detector's edges, which move through its planes all through a
    subscan, left alone). One whose support (the objective's rise were it removed) is positive in at most half the
    :func:`middle_views` (its median there is not positive) goes, and leaves no track: the subscan before finds
    it.

    Parameters
    ----------
    projector : MeshProjector
    residual : ndarray float64, ``projector.geometry.shape``
        ``Proj(after) - data``; updated in place for the bubbles taken out.
    ids : sequence of int
        The successor's track ids (the warm fit's).
    new_ids, after : list
        The bubbles after the detection and their track ids.
    lineage : dict
        :func:`~bubsub.clients.pipeline.dynamic4d.tracks.assign_tracks`'s (after :func:`merged_at_midtime`).

    Returns
    -------
    new_ids, after : list
        Without the bubbles taken out.
    lineage : dict
        Without their ``new`` entries.
    gone : dict
        ``{id: median support in the middle views}`` of the bubbles taken out.
    """
    skip = {int(i) for i in ids} | {int(i) for c in lineage["coalescences"] for i in c["children"]}
    geometry = projector.geometry
    middle = middle_views(geometry.n_angles)
    gone = {}
    for i, s in zip(new_ids, after):
        if int(i) in skip or edge_side(s, geometry) is not None:
            continue
        p = footprint(projector, s)
        support = float(np.median(p.removal_gains(residual)[middle]))
        if support <= 0:
            p.add_to(residual, -1.0)
            gone[int(i)] = support
    if not gone:
        return new_ids, after, lineage, {}
    keep = [k for k, i in enumerate(new_ids) if int(i) not in gone]
    lineage = dict(lineage, new={i: why for i, why in lineage["new"].items() if int(i) not in gone})
    return [new_ids[k] for k in keep], [after[k] for k in keep], lineage, gone
