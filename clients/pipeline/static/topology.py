"""Topology that adapts during the fit: bubbles added, removed, merged and split.

A BFGS fit keeps the number of bubbles it starts with, so a centre the
initialisation missed stays missing (a neighbour stretches over its gas) and
a spurious one stays. Between optimiser rounds :func:`adapt_topology` tries
changes and keeps each one only if the objective ``f = 0.5 ||Proj(S x) - d||^2``
improves:

* **remove**: the projection is a sum over bubbles, so with each bubble's own
  projection ``p_k`` the objective without it is ``0.5 ||r - p_k||^2``
  (``r = Proj - d``), exact and cheap; a bubble goes when that is not larger
  than ``f`` (collapsed or spurious bubbles), greedily, best first;
* **add**: the residual ``d - Proj`` is reconstructed on the preview grid
  (unexplained gas shows as bright blobs) and blobs found by
  :func:`bubsub.clients.pipeline.static.blobs.log_blobs` outside the existing
  bubbles become round bubbles, each kept when ``0.5 ||r + p_new||^2 < f``;
* **merge**: two touching bubbles are replaced by one round bubble of their
  joint size, fitted alone against the data minus the other bubbles, and
  kept when that beats the pair fitted the same way and the fitted bubble
  has no neck (:data:`MERGE_CONVEXITY`);
* **split**: a bubble that holds two blobs of the voxel preview (a neighbour
  grown over a bubble the initialisation missed), or an elongated one
  (second-moment axis ratio above ``split_ratio``, :func:`split_axis`), is replaced by two round
  bubbles (at the blobs, or along its long axis), fitted the same way, kept
  when better than the bubble itself.

Then the bubbles the round changed, and their neighbours, are refitted on
detector windows with the rest of the scene held fixed
(:func:`bubsub.clients.pipeline.regions.local.local_refit`: the cost of a round
follows what it changed, not the scan's size), and the next round starts;
it tries removals, merges and splits among the refitted bubbles only (the
rest of the scene is as the round before left it, which tried them). Every
accepted change is recorded with its objective before and after.

The module is one on purpose: the four steps and the round that drives them
share one residual and one set of bubble footprints, updated in place by
every accepted change; apart, each step would need that bookkeeping's
internals as public names.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from bubsub.core.projection.mesh import bounding_box, equivalent_radius
from bubsub.core.projection.subdivision import circle_surface, sphere_surface
from bubsub.core.projection.masks import bubble_mask, coverage
from bubsub.core.voxel.grid import world_to_index

from bubsub.clients.pipeline.static.blobs import log_blobs
from bubsub.clients.pipeline.inputs.fov import preview_extension
from bubsub.clients.pipeline.regions.local import (LOCAL_RTOL, Footprints, footprint, local_fits, local_refit,
                                                   others_removed, scene_objective, scene_residual)
from bubsub.clients.pipeline.static.preview import preview_grid, resample_image, voxel_preview
from bubsub.clients.pipeline.static.resolution import levels_by_size
from bubsub.clients.pipeline.inputs.fov import field_of_view, fov_report, truncated_flags, unobserved_control
from bubsub.clients.progress import phase

__all__ = ["adapt_topology", "adapt_bubbles", "add_at", "split_step", "replace_by_one", "replace_by_two",
           "unknowns_cost", "points_inside", "convexity", "touching_pairs", "merge_trial", "round_bubble_maker",
           "MERGE_CONVEXITY"]

#: BB iterations of the 3D residual preview (half the data preview's 30): the residual's blobs are bright
#: enough for the add step after 15 (a bubble left out of a fit is added at the same place as with 30),
#: for less of the add step's time
RESIDUAL_PREVIEW_ITERATIONS_3D = 15

#: Least convexity (:func:`convexity`) of the one bubble that replaces a merged pair. A bubble of a foam is
#: convex (round in a wet foam, a polyhedron of nearly flat films in a dry one); fitted alone to the data of two
#: touching bubbles, the one bubble keeps their neck: the union of two touching discs fills 0.88 of its convex
#: hull, of two touching balls 0.80 (equal sizes), and the merged bubbles fitted to such pairs fill 0.69-0.94
#: (one in a hundred 0.997, its fit far worse than the pair's; docs/prepare.md), while a bubble fitted to the
#: data of one bubble seeded as two pieces fills 1.00. Without
#: this test the objective alone decides, and two touching bubbles whose merged fit is worse by less than the
#: Akaike credit of the unknowns it saves are merged (``python -m bubsub.bench fov --inside 5``).
MERGE_CONVEXITY = 0.95


def _half_sq(r):
    return 0.5 * float(np.vdot(r, r))


def _size(s):
    return abs(s.fine().size)


def _centre(s):
    return np.asarray(s.fine().centroid, dtype=float)


def remove_step(surfaces, residual, own, changes, round_no, cost=0.0, only=None):
    """Greedy removal of bubbles whose removal raises ``0.5 ||r||^2`` by at most ``cost`` (in place on ``residual``).

    ``cost`` is one number, or one per bubble (a bubble cut by the field of
    view's edge is charged only for the unknowns the data see). Every
    bubble's gain (of the bubbles ``only``, when given) is computed once from
    its footprint (not kept); the candidates' gains are computed again, best
    first, after each removal.
    """
    limit = np.broadcast_to(np.asarray(cost, dtype=float), (len(surfaces),))
    candidates = [k for k in (range(len(surfaces)) if only is None else sorted(only))
                  if own.compute(k).removal_gain(residual) <= limit[k]]
    gone = set()
    while candidates:
        f = _half_sq(residual)
        gains = [own[k].removal_gain(residual) - limit[k] for k in candidates]
        best = int(np.argmin(gains))
        if gains[best] > 0:
            break
        k = candidates.pop(best)
        own[k].add_to(residual, -1.0)
        gone.add(k)
        changes.append({"round": round_no, "change": "remove", "centre": _centre(surfaces[k]).tolist(),
                        "objective_before": f, "objective_after": f + gains[best] + limit[k]})
    alive = [k for k in range(len(surfaces)) if k not in gone]
    return [surfaces[k] for k in alive], own.subset(alive)


def add_step(projector, surfaces, residual, own, preview, new_bubble, changes, round_no, *, min_radius, max_radius,
             threshold, max_add, cost=0.0):
    """Round bubbles at blobs of the back-projected residual, each kept when the objective drops."""
    image, extent = preview(-residual.astype(np.float32))
    ndim = image.ndim
    if surfaces:
        occupied = bubble_mask(surfaces, image.shape, extent)
    else:
        occupied = np.zeros(image.shape, dtype=bool)
    contrast = new_bubble(np.zeros(ndim), 1.0).attenuation
    centres, radii = log_blobs(image, extent, contrast, min_radius=min_radius, max_radius=max_radius,
                               threshold=threshold)
    idx = np.clip(np.round(world_to_index(centres, image.shape, extent)).astype(int), 0, np.array(image.shape) - 1)
    free = ~occupied[tuple(idx.T)] if len(centres) else np.zeros(0, bool)
    return add_at(projector, surfaces, residual, own, centres[free], radii[free], new_bubble, changes, round_no,
                  min_radius=min_radius, max_add=max_add, cost=cost)


def add_at(projector, surfaces, residual, own, centres, radii, new_bubble, changes, round_no, *, min_radius,
           max_add, cost=0.0):
    """Round bubbles at ``centres`` (k, ndim) with about ``radii`` (k,) (mm), each kept when the objective drops.

    Each radius is cut to 0.9 of the gap to the nearest bubble's surface (a centre closer than ``min_radius``
    to one is skipped), tried at 0.7, 1 and 1.3 times, and the best kept when it lowers ``0.5 ||r||^2`` by more
    than ``cost``; ``residual`` and ``own`` follow each bubble kept (in place), ``changes`` records it.
    """
    surfaces = list(surfaces)
    ndim = np.asarray(centres).shape[-1] if len(centres) else 0
    added = 0
    for c, r in zip(centres, radii):
        if added >= max_add:
            break
        if surfaces:  # keep clear of the existing bubbles
            gap = min(np.min(np.linalg.norm(s.fine().vertices - c, axis=1)) for s in surfaces)
            r = min(r, 0.9 * gap)
        if r < min_radius:
            continue
        f = _half_sq(residual)
        best = None
        for scale in (0.7, 1.0, 1.3):
            cand = new_bubble(c, r * scale)
            p = footprint(projector, cand)
            g = p.addition_gain(residual)
            if best is None or g < best[0]:
                best = (g, cand, p)
        if best[0] < -cost:
            g, cand, p = best
            p.add_to(residual)
            surfaces.append(cand)
            own.append(cand, p)
            added += 1
            changes.append({"round": round_no, "change": "add", "centre": np.asarray(c).tolist(),
                            "radius": float(equivalent_radius(_size(cand), ndim)),
                            "objective_before": f, "objective_after": f + g})
    return surfaces, own


def convexity(surface):
    """A bubble's size (area in 2D, volume in 3D) over its convex hull's, from its fine surface: 1 when convex."""
    fine = surface.fine()
    return abs(fine.size) / ConvexHull(np.asarray(fine.vertices, dtype=float)).volume


def touching_pairs(surfaces, touch, tried=None):
    """The pairs of bubbles whose fine surfaces come within ``touch`` (mm) of each other, nearest first.

    Parameters
    ----------
    surfaces : list of SubdivisionSurface
    touch : float
        mm.
    tried : callable(i, j) -> bool, optional
        Only the pairs it accepts are measured (``i < j``).

    Returns
    -------
    list of (float, int, int)
        ``(distance, i, j)``, sorted.
    """
    if len(surfaces) < 2:
        return []
    fines = [s.fine().vertices for s in surfaces]
    centres = np.array([v.mean(axis=0) for v in fines])
    radii = np.array([np.linalg.norm(v - c, axis=1).max() for v, c in zip(fines, centres)])
    pairs = []
    for i, j in cKDTree(centres).query_pairs(2 * float(radii.max()) + touch):
        if np.linalg.norm(centres[i] - centres[j]) > radii[i] + radii[j] + touch:
            continue
        if tried is not None and not tried(i, j):
            continue
        d = float(cKDTree(fines[i]).query(fines[j])[0].min())
        if d <= touch:
            pairs.append((d, i, j))
    return sorted(pairs)


def merge_trial(projector, surfaces, residual, own, i, j, new_bubble, iterations):
    """Bubbles ``i`` and ``j`` against one round bubble of their joint size at their size-weighted centre, each fitted
    to the data less the rest of the scene on one detector window: ``((pair, f_pair), (one, f_one))``, as
    :func:`~bubsub.clients.pipeline.regions.local.local_fits` returns them."""
    size = _size(surfaces[i]) + _size(surfaces[j])
    c = (_centre(surfaces[i]) * _size(surfaces[i]) + _centre(surfaces[j]) * _size(surfaces[j])) / size
    one = new_bubble(c, equivalent_radius(size, surfaces[i].ndim))
    return local_fits(projector, [[surfaces[i], surfaces[j]], [one]], others_removed(residual, own[i], own[j]),
                      iterations)


def merge_step(projector, surfaces, residual, own, data, new_bubble, changes, round_no, *, touch, iterations,
               max_tries, cost=0.0, at_edge=None, only=None, min_convexity=MERGE_CONVEXITY):
    """Replace touching pairs by one bubble when that fits the data better than the pair.

    The one bubble must also be convex to ``min_convexity`` (:func:`convexity`,
    :data:`MERGE_CONVEXITY`; 0 leaves the objective alone to decide): fitted
    to the data of two touching bubbles it keeps their neck.

    ``at_edge`` (one bool per bubble, optional): bubbles that reach the edge
    of the field of view, never merged. Such a bubble's part beyond the edge
    costs the objective nothing, so one round bubble of the pair's joint size
    can explain a cut bubble's visible part and its neighbour's about as well
    as the two (a neighbour absorbing a cut bubble): the comparison cannot
    tell them apart there. ``only`` (indices, optional): pairs with one of these bubbles only.
    """
    if len(surfaces) < 2:
        return surfaces, own

    def tried(i, j):
        return (at_edge is None or not (at_edge[i] or at_edge[j])) and (only is None or i in only or j in only)

    pairs = touching_pairs(surfaces, touch, tried)
    surfaces = list(surfaces)
    gone = set()
    for _, i, j in pairs[:max_tries]:
        if i in gone or j in gone:
            continue
        (pair, f_pair), (one, f_one) = merge_trial(projector, surfaces, residual, own, i, j, new_bubble, iterations)
        if f_one < f_pair + cost and (min_convexity <= 0 or convexity(one[0]) >= min_convexity):
            replace_by_one(projector, surfaces, residual, own, i, one[0])
            own[j].add_to(residual, -1.0)
            gone.add(j)
            changes.append({"round": round_no, "change": "merge", "centres": [_centre(pair[0]).tolist(),
                            _centre(pair[1]).tolist()], "objective_before": f_pair, "objective_after": f_one})
    keep = [k for k in range(len(surfaces)) if k not in gone]
    return [surfaces[k] for k in keep], own.subset(keep)


def _seen_unknowns(surfaces, geometry):
    """(n,) float: coordinates of each bubble's control vertices that some ray of ``geometry`` sees."""
    return np.array([s.vertices.shape[1] * float(np.count_nonzero(~unobserved_control(s, geometry)))
                     for s in surfaces])


def _at_edge(surfaces, geometry):
    """(n,) bool: the bubbles whose refined surface reaches the edge of the field of view (one pixel's margin)."""
    return [bool(f) for f in truncated_flags([s.fine() for s in surfaces], field_of_view(geometry),
                                             fov_report(geometry)["margin"])]


def split_axis(s, geometry):
    """A bubble's elongation for the split step: its second-moment axis ratio and its long axis (one standard
    deviation long).

    A 3D bubble cut by the detector's top or bottom edge plane is measured by
    its part in view, long axis over middle one: its shape beyond the edge is
    unseen (the fit leaves it as its start made it), and the part in view of
    a round bubble's cap is flat, so the long over the short axis calls every
    large bubble's cap elongated. Two caps that one bubble holds (side by side
    along the plane) and a neighbour swollen up into a cap (upright) are
    elongated by this ratio too.

    Parameters
    ----------
    s : SubdivisionSurface
    geometry : ScanGeometry

    Returns
    -------
    centre : (ndim,) float
        The mean of the refined surface's vertices.
    ratio : float
        1 for a degenerate bubble (no second split candidate).
    axis : (ndim,) float
    """
    v = s.fine().vertices
    c = v.mean(axis=0)
    w, u = np.linalg.eigh(np.cov((v - c).T))
    if geometry.ndim == 3:
        half = field_of_view(geometry)[1]
        seen = np.abs(v[:, 2]) <= half
        if 4 <= seen.sum() < len(v):
            w2, u2 = np.linalg.eigh(np.cov((v[seen] - v[seen].mean(axis=0)).T))
            if w2[1] <= 0:
                return c, 1.0, np.zeros(3)
            return c, float(np.sqrt(w2[-1] / w2[1])), u2[:, -1] * np.sqrt(w2[-1])
    if w[0] <= 0:
        return c, 1.0, np.zeros(len(c))
    return c, float(np.sqrt(w[-1] / w[0])), u[:, -1] * np.sqrt(w[-1])


def points_inside(surface, points):
    """Which of ``points`` (k, ndim) lie inside the fine surface (winding numbers on a one-point grid each).

    Points outside the surface's bounding box are outside without a winding
    number: the split step tests every preview blob against every bubble
    (3600 one-point grids at 60 bubbles, about a second), and few are near.
    """
    points = np.asarray(points, dtype=float)
    lo, hi = bounding_box(surface.vertices)
    out = np.all((points >= lo) & (points <= hi), axis=1)
    for k in np.nonzero(out)[0]:
        p = points[k]
        tiny = 1e-6
        extent = tuple(np.stack([p - tiny, p + tiny], axis=1).ravel())
        out[k] = coverage(surface, (1,) * len(p), extent).item() > 0
    return out


def replace_by_one(projector, surfaces, residual, own, k, one):
    """Bubble ``k`` replaced by ``one`` in ``surfaces``, ``own`` and ``residual`` (in place). The new bubble's
    own projection is taken on its window, not the whole detector's (three arrays of the scan's size would set
    the pipeline's peak memory on a large scan)."""
    p = footprint(projector, one)
    p.add_to(residual)
    own[k].add_to(residual, -1.0)
    surfaces[k] = one
    own.set(k, one, p)


def replace_by_two(projector, surfaces, residual, own, k, two):
    """A split's bookkeeping: ``two[0]`` takes bubble ``k``'s place in ``surfaces`` and ``own``, ``residual``
    follows both new bubbles (in place); returns ``(two[1], its footprint)`` for the caller to add."""
    p0, p1 = (footprint(projector, t) for t in two)  # on their windows, as in merge_step
    p0.add_to(residual)
    p1.add_to(residual)
    own[k].add_to(residual, -1.0)
    surfaces[k] = two[0]
    own.set(k, two[0], p0)
    return two[1], p1


def unknowns_cost(unknowns, residual):
    """The objective drop that ``unknowns`` more unknowns must bring (the Akaike rule): twice their number times
    the residual's half mean square per pixel (the noise variance, where the fit explains the bubbles)."""
    return unknowns * 2 * _half_sq(residual) / residual.size


def split_step(projector, surfaces, residual, own, data, new_bubble, changes, round_no, *, ratio, iterations,
               max_tries, cost=0.0, blobs=None, only=None, neck_convexity=0.0):
    """Replace a bubble by two when that fits the data better.

    Candidates: a bubble holding two or more ``blobs`` (centres, radii of the
    preview's blobs; the two strongest become the new bubbles), or an
    elongated one (axis ratio above ``ratio``; two bubbles along its long axis).
    The ``max_tries`` tried are the blob candidates first (two blobs in one
    bubble are the stronger evidence: in a foam of elongated bubbles the
    elongated candidates alone would fill the tries), then the most elongated.
    ``only`` (indices, optional): candidates among these bubbles only.

    A split is kept when the two lower the objective by more than ``cost``,
    or, with ``neck_convexity`` > 0, when the one bubble has a neck (its
    :func:`convexity` below ``neck_convexity``), lies inside the field of
    view (a cut bubble's shape beyond the edge is unseen) and the two fit
    the data at least as well: :func:`merge_step` would not have joined
    such a pair, so one bubble does not stand for it. Two touching bubbles
    with a thin film between them (about to coalesce) are told from one by
    little more than that film, and the comparison of two short local fits
    alone decides at the margin of ``cost``.
    """
    cand = []
    for k, s in enumerate(surfaces):
        if only is not None and k not in only:
            continue
        if blobs is not None and len(blobs[0]) > 1:
            inside = np.nonzero(points_inside(s.fine(), blobs[0]))[0]
            if len(inside) >= 2:
                (a, b), (ra, rb) = blobs[0][inside[:2]], blobs[1][inside[:2]]
                gap = float(np.linalg.norm(a - b))
                # never overlapping each other
                scale = min(1.0, 0.95 * gap / (ra + rb))
                cand.append((-np.inf, k, [(a, ra * scale), (b, rb * scale)]))
                continue
        c, elongation, axis = split_axis(s, projector.geometry)
        if elongation > ratio:
            half = min(equivalent_radius(_size(s) / 2, s.ndim), 0.95 * float(np.linalg.norm(axis)))
            cand.append((-elongation, k, [(c - axis, half), (c + axis, half)]))
    surfaces = list(surfaces)
    extra = []
    for _, k, children in sorted(cand, key=lambda t: t[0])[:max_tries]:
        s = surfaces[k]
        target = others_removed(residual, own[k])
        (single, f_single), (two, f_two) = local_fits(
            projector, [[s], [new_bubble(c, r) for c, r in children]], target, iterations)
        if f_two < f_single - cost or (f_two <= f_single and _has_neck(s, neck_convexity, projector.geometry)):
            extra.append(replace_by_two(projector, surfaces, residual, own, k, two))
            changes.append({"round": round_no, "change": "split", "centre": _centre(s).tolist(),
                            "objective_before": f_single, "objective_after": f_two})
    for s, p in extra:
        surfaces.append(s)
        own.append(s, p)
    return surfaces, own


def _has_neck(surface, min_convexity, geometry):
    """Whether a bubble inside the field of view is less convex than ``min_convexity`` (0: never)."""
    return min_convexity > 0 and convexity(surface) < min_convexity and not _at_edge([surface], geometry)[0]


def _among(surfaces, ids):
    """Indices of ``surfaces`` whose ids are in ``ids`` (None: all, as None).

    A later topology round tries removals, merges and splits only where the last refit moved bubbles:
    elsewhere the scene is as the round before left it, which chose and tried the same candidates.
    """
    return None if ids is None else {k for k, s in enumerate(surfaces) if id(s) in ids}


def _changes_words(changes):
    """A round's changes in words, for its progress line: ``"2 added, 1 merged"``."""
    done = {"remove": "removed", "add": "added", "merge": "merged", "split": "split"}
    counts = {}
    for c in changes:
        counts[c["change"]] = counts.get(c["change"], 0) + 1
    return ", ".join(f"{n} {done[k]}" for k, n in counts.items()) or "no change"


def adapt_topology(projector, surfaces, data, *, preview, new_bubble, min_radius, max_radius, rounds=3,
                   iterations=30, threshold=0.15, touch=0.0, split_ratio=1.6, local_iterations=15, max_add=20,
                   max_tries=8, steps=("remove", "add", "merge", "split"), complexity=1.0, image=None,
                   progress=False, penalty=None, fov_edge=False, merge_convexity=MERGE_CONVEXITY,
                   refit_rtol=LOCAL_RTOL, after_removals=True, residual=None):
    """Alternate topology changes and joint BFGS fits.

    Parameters
    ----------
    projector : MeshProjector
        Of the fitted projections (local: changes need single-bubble projections).
    surfaces : list of SubdivisionSurface
        Bubbles after a first fit.
    data : ndarray
        Projections, ``projector.geometry.shape``.
    preview : callable(projections) -> (image, extent)
        Voxel reconstruction of a projection array (bubbles positive), e.g.
        :func:`bubsub.clients.pipeline.static.preview.voxel_preview` with the
        scan's geometry and contrast.
    new_bubble : callable(centre, radius) -> SubdivisionSurface
        A round bubble with the fit's topology.
    min_radius, max_radius : float
        Range of radii of added bubbles, mm.
    rounds : int
        Rounds of (changes, joint fit); stops early when a round changes nothing.
    iterations : int
        BFGS iterations of each local refit of the changed bubbles and their neighbours.
    threshold : float
        Least LoG response of a residual blob, as a fraction of ``|contrast|``.
    touch : float
        Bubbles closer than this (mm) are merge candidates.
    split_ratio : float
        Least long/short axis ratio of a split candidate.
    local_iterations, max_add, max_tries : int
        BFGS iterations of the local fits that decide merges and splits;
        most bubbles added per round; most merge and split candidates tried per round.
    steps : tuple of str
        Which changes to try.
    image : (ndarray, extent), optional
        The voxel preview of the data; a bubble that holds two of its blobs
        is a split candidate.
    complexity : float
        A change that adds a bubble must lower the objective, and one that
        removes a bubble may raise it, by at most ``complexity x k x sigma^2``,
        with ``k`` the bubble's unknowns and ``sigma^2 = 2 f / m`` the mean
        squared residual of the ``m`` data values before the round (the
        Akaike criterion for ``complexity = 1``): without it, two bubbles
        always fit noise a little better than one.
    penalty : callable, optional
        Added to the objective of the joint fits (:func:`bubsub.clients.optimise.fit`).
    fov_edge : bool
        Respect the edge of the field of view (:mod:`bubsub.clients.pipeline.inputs.fov`): a
        bubble that reaches it is never merged, and its removal is weighed
        against the unknowns the data see (its control vertices that some ray
        sees), not all of them, so that a cut bubble whose visible part is small
        is kept when it explains that part.
    merge_convexity : float
        Least convexity of the bubble that replaces a merged pair (:func:`merge_step`'s ``min_convexity``).
    refit_rtol : float
        The convergence test of each round's refit (:func:`~bubsub.clients.pipeline.regions.local.local_refit`'s
        ``rtol``).
    after_removals : bool
        Whether a round that only removed bubbles is followed by another. A removed bubble explained less than
        its unknowns cost, so what it leaves in the residual cannot pay for a new one, and the next round finds
        what this one did not only where the refit of its neighbours moves them.
    residual : ndarray float64, optional
        ``Proj(surfaces) - data`` if known (updated in place); else computed with one projection. Each round
        after the first starts from the residual its predecessor's changes and refit kept up to date.

    Returns
    -------
    surfaces : list of SubdivisionSurface
    summary : dict
        ``changes`` (each with round, kind, where, objective before and
        after), ``objective`` (final), ``rounds`` (done), ``evaluations``.
    """
    surfaces = list(surfaces)
    data = np.asarray(data)
    changes = []
    done = 0
    blobs = None
    if image is not None and "split" in steps:
        contrast = new_bubble(np.zeros(data.ndim if not surfaces else surfaces[0].ndim), 1.0).attenuation
        blobs = log_blobs(image[0], image[1], contrast, min_radius=min_radius, max_radius=max_radius,
                          threshold=threshold)
    unknowns = new_bubble(np.zeros(surfaces[0].ndim if surfaces else data.ndim), 1.0).vertices.size
    refits = []
    fresh = None  # after the first round: the bubbles the last refit moved (ids)

    for r in range(rounds):
        n_before = len(changes)
        start = {id(s): s for s in surfaces}
        # the whole round is one phase, timed from its start: its changes (the residual's blobs, the merge and
        # split trials) take most of its time, the refit of what they changed (a phase of its own) the rest
        with phase(f"topology round {r + 1}", len(steps) + 1, unit="step", enabled=progress) as bar:
            own = Footprints(projector, surfaces)
            if residual is None:
                residual = scene_residual(projector, surfaces, data)
            cost = unknowns_cost(complexity * unknowns, residual)
            if "remove" in steps:
                # unknowns no ray sees cost nothing to remove: a cut bubble is charged for its visible ones only
                removal_cost = cost * _seen_unknowns(surfaces, projector.geometry) / unknowns if fov_edge else cost
                surfaces, own = remove_step(surfaces, residual, own, changes, r, removal_cost,
                                            only=_among(surfaces, fresh))
                bar.update(1)
            if "add" in steps:
                surfaces, own = add_step(projector, surfaces, residual, own, preview, new_bubble, changes, r,
                                         min_radius=min_radius, max_radius=max_radius, threshold=threshold,
                                         max_add=max_add, cost=cost)
                bar.update(1)
            if "merge" in steps:
                at_edge = _at_edge(surfaces, projector.geometry) if fov_edge else None
                surfaces, own = merge_step(projector, surfaces, residual, own, data, new_bubble, changes, r,
                                           touch=touch, iterations=local_iterations, max_tries=max_tries, cost=cost,
                                           at_edge=at_edge, only=_among(surfaces, fresh),
                                           min_convexity=merge_convexity)
                bar.update(1)
            if "split" in steps:
                surfaces, own = split_step(projector, surfaces, residual, own, data, new_bubble, changes, r,
                                           ratio=split_ratio, iterations=local_iterations, max_tries=max_tries,
                                           cost=cost, blobs=blobs, only=_among(surfaces, fresh))
                bar.update(1)
            done = r + 1
            if len(changes) == n_before or not surfaces:
                bar.close("no change")
                break
            # only the bubbles the round changed, and their neighbours, are refitted (on windows, the rest fixed)
            kept = {id(s) for s in surfaces}
            changed = [k for k, s in enumerate(surfaces) if id(s) not in start]
            gone = [(_centre(s), equivalent_radius(_size(s), s.ndim)) for i, s in start.items() if i not in kept]
            before_refit = {id(s) for s in surfaces}
            surfaces, residual, summary = local_refit(projector, surfaces, data, changed, iterations=iterations,
                                                      touch=touch, near=gone, residual=residual, penalty=penalty,
                                                      progress=progress, label=f"topology round {r + 1} refit",
                                                      rtol=refit_rtol)
            fresh = {id(s) for s in surfaces if id(s) not in before_refit}
            refits.append(dict(summary, round=r))
            bar.update(1)
            bar.close(_changes_words(changes[n_before:]))
            if not after_removals and all(c["change"] == "remove" for c in changes[n_before:]):
                break
    # the last round's residual is the returned scene's (kept up to date by every change and refit)
    objective = _half_sq(residual) if residual is not None else scene_objective(projector, surfaces, data)
    return surfaces, {"changes": changes, "objective": objective, "rounds": done, "refits": refits}


def round_bubble_maker(surfaces, geometry, contrast, levels, facet_pixels):
    """``new_bubble(centre, radius)``: a round bubble of ``contrast`` (1/mm) with ``surfaces``' control mesh (their
    number of control points; in 3D 42 unless it is 12, 42 or 162), in 2D at their subdivision levels, in 3D
    subdivided by its size as the fitted bubbles are (at most ``levels``, faces within ``facet_pixels``:
    :func:`~bubsub.clients.pipeline.static.resolution.levels_by_size` on ``geometry``)."""
    k = len(surfaces[0].vertices)
    if surfaces[0].ndim == 2:
        curve_levels = surfaces[0].levels
        return lambda c, r: circle_surface(c, r, contrast, control=k, levels=curve_levels)
    k = k if k in (12, 42, 162) else 42
    return lambda c, r: levels_by_size([sphere_surface(c, r, contrast, control=k, levels=levels)], geometry, levels,
                                       facet_pixels)[0]


def adapt_bubbles(projector, surfaces, data, *, contrast, voxel, rounds, iterations, levels, facet_pixels,
                  voxel_size=None, method="box", fov_model=True, image=None, extent=None, penalty=None,
                  progress=False, steps=("remove", "add", "merge", "split"), unexplained_only=False,
                  refit_rtol=LOCAL_RTOL, after_removals=True, residual=None):
    """:func:`adapt_topology` as the reconstruction pipeline runs it (its preview's grid and new bubbles).

    Parameters
    ----------
    projector : MeshProjector
        Local, of the fitted projections ``data``; ``surfaces`` are the bubbles after the first fit.
    contrast : float
        1/mm, the new bubbles'.
    voxel : float
        The voxel preview's voxel size, mm: added bubbles are at least 3 voxels in radius, bubbles within 2
        voxels are merge candidates, a 3D residual is reconstructed on voxels twice as large.
    rounds, iterations : int
        Topology rounds; the fit's iteration cap (each refit of a round runs ``max(10, iterations // 2)``).
    levels, facet_pixels
        The most subdivision levels of a new bubble, in 3D as few as keep its faces within ``facet_pixels``
        (:func:`~bubsub.clients.pipeline.static.resolution.levels_by_size`); in 2D the fitted bubbles' levels.
    voxel_size, method, fov_model
        The preview's options (``--voxel-size``, its 2D residual preview's voxel; ``--preview``; the field of
        view model, which :func:`adapt_topology` then respects, ``fov_edge``).
    image, extent : optional
        The voxel preview and its extent (mm); None where there is none (a warm-started subscan of
        ``reconstruct4d``): no split candidates from its blobs.
    penalty, progress, steps
        As :func:`adapt_topology`'s.
    unexplained_only : bool
        Reconstruct only the residual's part of the bubbles' sign (gas the bubbles leave unexplained), the
        rest set to 0: where fitted bubbles stand a little too large, the residual's other sign, which the
        preview's ``x >= 0`` cannot hold, washes out the blobs beside them (a warm fit's neighbours that grew
        toward a bubble they have no start for).
    refit_rtol, after_removals, residual
        As :func:`adapt_topology`'s.

    Returns
    -------
    surfaces, summary
        As :func:`adapt_topology`'s.
    """
    geometry = projector.geometry
    ndim = surfaces[0].ndim
    new_bubble = round_bubble_maker(surfaces, geometry, contrast, levels, facet_pixels)

    # In 3D the residual is reconstructed, and blobs are searched, on voxels twice as large:
    # an added bubble is at least 3 preview voxels in radius, and a full-size residual
    # preview with its blob search cost as much as the first fit and 400 MB of scale space
    coarse = 2 * voxel if ndim == 3 else voxel_size
    extend = preview_extension(fov_model, data, contrast)  # as the data preview's
    if ndim == 3 or image is None:
        shape_c, extent_c = preview_grid(geometry, coarse, extend)
        if image is not None:
            image = resample_image(image, extent, shape_c, extent_c)
        extent = extent_c

    def preview(projections):
        if unexplained_only:
            projections = np.where(np.sign(contrast) * projections > 0, projections, np.float32(0))
        return voxel_preview(projections, geometry, contrast, coarse, method=method, coarse_3d=False,
                             extend=extend, iterations=RESIDUAL_PREVIEW_ITERATIONS_3D if ndim == 3 else None)

    size = extent[1] - extent[0]
    return adapt_topology(projector, surfaces, data, preview=preview, new_bubble=new_bubble, min_radius=3 * voxel,
                          max_radius=size / 8, rounds=rounds, iterations=max(10, iterations // 2), touch=2 * voxel,
                          image=None if image is None else (image, extent), progress=progress, penalty=penalty,
                          fov_edge=fov_model, steps=steps, refit_rtol=refit_rtol, after_removals=after_removals,
                          residual=residual)
