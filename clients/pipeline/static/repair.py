"""Repair of invalid fitted bubbles: self-intersecting outlines and interpenetrating pairs.

The fit minimises the projection distance only, so at few views it can
return an outline that crosses itself (its shoelace area, and the CSV row,
would be wrong) or two bubbles that share gas (counted twice). After the fit,
:func:`repair_bubbles` checks (:func:`bubsub.core.projection.validity.check_bubbles`)
and acts:

* a self-intersecting bubble is untangled by Laplacian smoothing of the
  control vertices around its crossings ("unfolded"), else of all its control
  vertices, its size kept ("smoothed"), or, where a dozen smoothing steps do
  not untangle it, replaced by a round one with its centre and root-mean-square
  radius ("rounded");
* two interpenetrating bubbles are separated by a plane halfway through their
  overlap, perpendicular to the line between their centres: the control
  vertices beyond a plane parallel to it are moved onto that plane, which is
  placed (by bisection) so that each fine surface ends ``gap / 2`` short of
  the middle one ("separated"). Loop and cubic B-spline subdivision are
  convex combinations of control vertices, so clipping at the middle plane
  itself would always suffice; the bisection only moves less;
* a bubble wholly inside another, or turned inside out, is dropped ("dropped").

Before the check, the part of each bubble that no ray sees (beyond the
detector's top or bottom row: control vertices whose refined neighbourhood
no projection sees, :func:`bubsub.clients.pipeline.inputs.fov.unobserved_control`)
is continued from the part the data determine (:func:`continued`): the fit
leaves those vertices where the bubble started, so when the visible part
has moved or grown they would fold into it (collapse) or stand off it
(swell), and an unseen part of the wrong size overlaps a neighbour's and
makes the repair move the neighbours' visible parts.

Then a short refit lets the data reshape the repaired bubbles; the refit may
undo a repair, so the check and the repairs run again (up to ``rounds``
times) and the last round repairs without refitting. The smaller bubble of a
pair still sharing gas after that is shrunk about its centre by a few per
cent ("shrunk", :data:`SHRINK_STEPS`); a bubble still invalid after that is
dropped. Every action is recorded, and the final check's
violations are returned, so the report says what was wrong and what was done.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.linalg import spsolve

from bubsub.core.projection.subdivision import circle_surface, sphere_surface
from bubsub.core.projection.validity import check_bubbles, self_crossing_vertices, self_crossings
from bubsub.clients.pipeline.inputs.fov import unobserved_control
from bubsub.clients.pipeline.regions.local import local_refit, scene_objective

__all__ = ["check_and_repair", "merged_validity", "repair_bubbles", "rounded", "untangled", "separate", "continued",
           "shrunk", "shrink_overlaps",
           "MIN_SEEN"]


def _centre_radius(surface):
    fine = surface.fine().vertices
    c = fine.mean(axis=0)
    return c, float(np.sqrt(np.mean(np.sum((fine - c) ** 2, axis=1))))


def rounded(surface):
    """A round bubble with ``surface``'s centre, RMS radius and number of control vertices."""
    c, r = _centre_radius(surface)
    n = len(surface.vertices)
    if surface.ndim == 2:
        new = circle_surface(c, r, surface.attenuation, control=n, levels=surface.levels)
    elif n in (12, 42, 162) and np.array_equal(
            sphere_surface(c, r, surface.attenuation, control=n, levels=surface.levels).control_faces,
            surface.control_faces):
        new = sphere_surface(c, r, surface.attenuation, control=n, levels=surface.levels)
    else:
        # another topology (a user's initial mesh): push the control vertices onto a sphere
        d = surface.vertices - surface.vertices.mean(axis=0)
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        return surface.with_vertices(c + r * d / np.where(norm > 0, norm, 1.0))
    return surface.with_vertices(new.vertices) if new.vertices.shape == surface.vertices.shape else new


def _control_edges(surface):
    """Directed control edges ``(k, 2)``: each neighbour pair in both directions."""
    if surface.ndim == 2:
        i = np.arange(len(surface.vertices))
        nxt = np.roll(i, -1)
        return np.concatenate([np.stack([i, nxt], 1), np.stack([nxt, i], 1)])
    f = surface.control_faces
    return np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])


#: Least fraction of a bubble's control vertices that the data see for its unseen part to be continued from
#: them (:func:`continued`); below it the sphere the bubble started as is the better guess.
MIN_SEEN = 0.25


def continued(surface, unseen):
    """The bubble with its unseen control vertices continued from the seen ones: a sphere and a smooth rest.

    A sphere is fitted (least squares, algebraic) to the seen control
    vertices; every unseen one is put on it along its own direction from the
    sphere's centre, plus the seen vertices' offsets from the sphere extended
    harmonically over the control mesh (each unseen offset the mean of its
    neighbours'), so the continuation meets the visible part without a kink
    and is as round as a sphere beyond it: it neither folds in nor swells.

    Parameters
    ----------
    surface : SubdivisionSurface
    unseen : (n_control,) bool
        Control vertices no ray sees (:func:`bubsub.clients.pipeline.inputs.fov.unobserved_control`).

    Returns
    -------
    SubdivisionSurface
        ``surface`` itself when nothing is unseen, fewer than :data:`MIN_SEEN`
        of the vertices (or fewer than ``ndim + 3``) are seen, or the sphere
        fit is degenerate (radius outside half to twice the seen vertices'
        median distance from its centre).
    """
    v = np.asarray(surface.vertices, dtype=float)
    unseen = np.asarray(unseen, dtype=bool)
    seen = ~unseen
    n, d = v.shape
    if not unseen.any() or seen.sum() < max(d + 3, MIN_SEEN * n):
        return surface
    x = v[seen]
    a = np.c_[2 * x, np.ones(len(x))]
    sol, *_ = np.linalg.lstsq(a, np.einsum("ij,ij->i", x, x), rcond=None)
    c = sol[:d]
    r2 = sol[d] + c @ c
    spread = float(np.median(np.linalg.norm(x - c, axis=1)))
    if not (np.isfinite(r2) and r2 > 0 and 0.5 * spread <= np.sqrt(r2) <= 2 * spread):
        return surface
    rho = np.sqrt(r2)
    out = v - c
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    ref = c + rho * out / np.where(norm > 0, norm, 1.0)
    offset = v - ref
    e = _control_edges(surface)
    adj = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    adj.data[:] = 1.0  # an edge listed twice is one neighbour
    lap = (coo_matrix((np.asarray(adj.sum(axis=1)).ravel(), (np.arange(n), np.arange(n))), shape=(n, n)) - adj)
    lap = lap.tocsr()
    u, s_ = np.flatnonzero(unseen), np.flatnonzero(seen)
    rhs = -(lap[u][:, s_] @ offset[s_])
    inner = lap[u][:, u].tocsc()
    filled = np.column_stack([spsolve(inner, rhs[:, k]) for k in range(d)])
    w = v.copy()
    w[u] = ref[u] + filled
    return surface.with_vertices(w)


def _grown(surface, mask):
    """``mask`` with the control neighbours of its vertices added."""
    e = _control_edges(surface)
    out = mask.copy()
    out[e[mask[e[:, 0]], 1]] = True
    return out


def _neighbour_mean(surface):
    v = surface.vertices
    if surface.ndim == 2:
        return 0.5 * (np.roll(v, 1, axis=0) + np.roll(v, -1, axis=0))
    e = _control_edges(surface)
    total = np.zeros_like(v)
    np.add.at(total, e[:, 0], v[e[:, 1]])
    count = np.bincount(e[:, 0], minlength=len(v))[:, None]
    return total / np.maximum(count, 1)


def _tangled_control(surface):
    """Boolean mask of the control vertices at a self-crossing of the control surface or that move the fine
    surface's crossing vertices."""
    mask = np.zeros(len(surface.vertices), dtype=bool)
    mask[self_crossing_vertices(surface.control)] = True
    fine = self_crossing_vertices(surface.fine())
    if len(fine):
        mask[surface.S[fine].nonzero()[1]] = True
    return mask


#: a fold is undone locally when the control vertices at its crossings are at most this fraction of all
LOCAL_FOLD = 0.25


def _unfolded(surface, steps, weight):
    """Laplacian smoothing of only the control vertices around the crossings (a region growing by one ring
    of neighbours each step) until neither surface crosses itself; None if that takes more than ``steps``
    or the crossings involve more than :data:`LOCAL_FOLD` of the control vertices."""
    region = _tangled_control(surface)
    if not region.any() or region.sum() > LOCAL_FOLD * len(region):
        return None  # not a local fold (e.g. on a coarse control mesh): smooth the whole bubble
    s = surface
    for _ in range(steps):
        region = _grown(s, region)
        v = s.vertices.copy()
        v[region] += weight * (_neighbour_mean(s)[region] - v[region])
        s = s.with_vertices(v)
        if not self_crossings(s.control) and not self_crossings(s.fine()):
            return s
    return None


def untangled(surface, steps=12, weight=0.5):
    """Laplacian smoothing of the control vertices until neither surface crosses itself, else :func:`rounded`.

    Smoothing removes the fold that makes an outline cross itself while
    keeping the bubble's size and position, and mostly its shape (a dense
    foam's flattened faces). It first smooths only the control vertices
    around the crossings (a local fold, e.g. at a Plateau border of a control
    mesh refined by :mod:`bubsub.clients.pipeline.static.refine`, is undone without
    rounding the rest of the bubble: ``"unfolded"``), then all of them
    (``"smoothed"``); rounding is the fallback.

    Returns
    -------
    (SubdivisionSurface, str)
        The repaired bubble and ``"unfolded"``, ``"smoothed"`` or ``"rounded"``.
    """
    local = _unfolded(surface, steps, weight)
    if local is not None:
        return local, "unfolded"
    s = surface
    for _ in range(steps):
        s = s.with_vertices(s.vertices + weight * (_neighbour_mean(s) - s.vertices))
        if not self_crossings(s.control) and not self_crossings(s.fine()):
            # smoothing shrinks: restore the control vertices' RMS distance from their mean
            # (the tangled fine surface's own size is what is wrong)
            def rms(v):
                return float(np.sqrt(np.mean(np.sum((v - v.mean(axis=0)) ** 2, axis=1))))

            c = s.vertices.mean(axis=0)
            scale = rms(surface.vertices) / rms(s.vertices)
            return s.with_vertices(c + (s.vertices - c) * scale), "smoothed"
    return rounded(surface), "rounded"


def _clip_below(surface, n, limit, steps=20):
    """Move control vertices onto the plane ``x . n = c`` for the largest ``c`` that keeps the fine surface at ``<= limit``.

    Control vertices lie outside the subdivided surface, so clipping them at
    ``limit`` itself would flatten the fine surface short of it; bisection on
    the clipping plane leaves the fine surface just touching ``limit``.
    """
    v = surface.vertices
    proj = v @ n
    S = surface.S

    def clipped(c):
        w = v.copy()
        t = proj - c
        w[t > 0] -= t[t > 0, None] * n
        return w

    if float(np.max(S @ proj)) <= limit:
        return surface
    lo, hi = limit, float(proj.max())  # clipping at lo keeps the fine surface below limit (convex hull)
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        if float(np.max(S @ (clipped(mid) @ n))) <= limit:
            lo = mid
        else:
            hi = mid
    return surface.with_vertices(clipped(lo))


def separate(a, b, gap=0.0):
    """Move the control vertices of two overlapping bubbles apart across a plane.

    The plane is perpendicular to the line between the bubbles' centres,
    halfway through their overlap; each bubble's fine surface ends up
    ``gap / 2`` short of it, moved no further than that needs.

    Parameters
    ----------
    a, b : SubdivisionSurface
    gap : float
        Film thickness left between them, mm.

    Returns
    -------
    (SubdivisionSurface, SubdivisionSurface)
    """
    fa, fb = a.fine().vertices, b.fine().vertices
    n = fb.mean(axis=0) - fa.mean(axis=0)
    length = np.linalg.norm(n)
    n = n / length if length > 0 else np.eye(a.ndim)[0]
    # the plane halfway through the overlap along n
    p = 0.5 * (float(np.max(fa @ n)) + float(np.min(fb @ n)))
    return _clip_below(a, n, p - gap / 2), _clip_below(b, -n, -(p + gap / 2))


def _size(surface):
    return abs(surface.fine().size)


def _repair_once(surfaces, violations, gap, actions, round_no):
    surfaces = list(surfaces)
    drop = set()
    tangled = {}
    for v in violations:
        if v.kind == "self_intersection":
            tangled.setdefault(v.bubbles[0], []).append(v.surface)
    for v in violations:
        if v.kind == "inverted":
            drop.add(v.bubbles[0])
            actions.append({"round": round_no, "action": "dropped", "bubble": v.bubbles[0], "reason": "inside out"})
    for i, which in sorted(tangled.items()):
        surfaces[i], how = untangled(surfaces[i])
        actions.append({"round": round_no, "action": how, "bubble": i, "surfaces": which})
    for v in violations:
        if v.kind != "overlap":
            continue
        i, j = v.bubbles
        if i in drop or j in drop:
            continue
        if v.crossings == 0:  # no boundary crossing but shared gas: one inside the other
            k = i if _size(surfaces[i]) < _size(surfaces[j]) else j
            drop.add(k)
            actions.append({"round": round_no, "action": "dropped", "bubble": k, "reason": "inside another bubble"})
            continue
        surfaces[i], surfaces[j] = separate(surfaces[i], surfaces[j], gap)
        actions.append({"round": round_no, "action": "separated", "bubbles": [i, j], "overlap": v.measure})
    return surfaces, drop


#: Scale factors tried, in turn, on the smaller bubble of a pair that still shares gas after the last separation.
SHRINK_STEPS = (0.98, 0.96, 0.93, 0.9, 0.85, 0.8)


def shrunk(surface, factor):
    """``surface`` scaled by ``factor`` about the centroid of its fine vertices (its shape kept)."""
    c = surface.fine().vertices.mean(axis=0)
    return surface.with_vertices(c + factor * (surface.vertices - c))


def shrink_overlaps(surfaces, violations, actions, round_no):
    """Shrink the smaller bubble of each pair still sharing gas (:data:`SHRINK_STEPS`) until the pair is
    valid; the violations that remain (the others, and pairs no step frees) are returned.

    A separation that leaves a sliver of shared gas (a bubble pressed against
    several neighbours, each separation moving it into the next) would
    otherwise cost the bubble: dropping it loses its gas from the projection,
    which no refit of its neighbours can restore.
    """
    surfaces = list(surfaces)
    remaining, changed = [], set()
    for v in violations:
        if v.kind != "overlap" or len(v.bubbles) != 2:
            remaining.append(v)
            continue
        i, j = v.bubbles
        k, other = (i, j) if _size(surfaces[i]) < _size(surfaces[j]) else (j, i)
        if changed & {i, j} and not check_bubbles([surfaces[k], surfaces[other]]):
            continue  # freed by an earlier pair's shrinking
        for factor in SHRINK_STEPS:
            trial = shrunk(surfaces[k], factor)
            if not check_bubbles([trial, surfaces[other]]):
                surfaces[k] = trial
                changed.add(k)
                actions.append({"round": round_no, "action": "shrunk", "bubble": k, "factor": factor,
                                "overlap": v.measure})
                break
        else:
            remaining.append(v)
    if changed:  # a shrunk bubble may still meet a third one: check again what involves them
        keep = [v for v in remaining if not changed & set(v.bubbles)]
        remaining = keep + check_bubbles(surfaces, only=sorted(changed))
    return surfaces, remaining


def repair_bubbles(surfaces, refit=None, *, gap=0.0, rounds=2):
    """Check fitted bubbles and repair what is invalid.

    Parameters
    ----------
    surfaces : list of SubdivisionSurface
    refit : callable(surfaces, changed, gone) -> list of SubdivisionSurface, optional
        A short fit after each repair round (not after the last): ``changed`` are the indices of the
        repaired bubbles, ``gone`` ``(centre, radius)`` of the dropped ones.
    gap : float
        Liquid film left between separated bubbles, mm.
    rounds : int
        Repair rounds (each: check, repair, refit).

    Returns
    -------
    surfaces : list of SubdivisionSurface
        Valid bubbles (indices change where bubbles were dropped).
    summary : dict
        ``violations_found`` (the first check, as dicts), ``actions`` (each
        with its round; bubble indices refer to the list entering that
        round), ``violations_remaining`` (the final check, empty unless a
        repair failed and the bubble could not be dropped), ``dropped``.
    """
    surfaces = list(surfaces)
    actions = []
    found = check_bubbles(surfaces)
    violations = found
    dropped = 0
    for r in range(rounds + 1):
        if not violations:
            break
        last = r == rounds
        before = list(surfaces)
        surfaces, drop = _repair_once(surfaces, violations, gap, actions, r)
        # every violating bubble was repaired (changed) or dropped: only the changed can still be invalid
        violations = check_bubbles(surfaces, only=[k for k, s in enumerate(surfaces) if s is not before[k]]) \
            if last else []
        if last and violations:
            # a pair still sharing gas: shrink the smaller about its centre rather than lose it
            surfaces, violations = shrink_overlaps(surfaces, violations, actions, r)
        bad = {b for v in violations for b in v.bubbles}
        if last and bad:
            # still invalid after repairing without a refit: drop the offenders (the smaller of a pair)
            for v in violations:
                k = v.bubbles[0] if len(v.bubbles) == 1 else min(v.bubbles, key=lambda b: _size(surfaces[b]))
                if k not in drop:
                    drop.add(k)
                    actions.append({"round": r, "action": "dropped", "bubble": k, "reason": f"still {v.kind}"})
        gone = [_centre_radius(before[k]) for k in sorted(drop)]
        changed = [k for k, s in enumerate(surfaces) if s is not before[k] and k not in drop]
        if drop:
            dropped += len(drop)
            keep = [k for k in range(len(surfaces)) if k not in drop]
            changed = [keep.index(k) for k in changed]
            surfaces = [surfaces[k] for k in keep]
        if not last and refit is not None and surfaces:
            kept = list(surfaces)
            surfaces = list(refit(surfaces, changed, gone))
            changed = sorted(set(changed) | {k for k, s in enumerate(surfaces) if s is not kept[k]})
        # only what changed can have become invalid (a dropped bubble leaves its neighbours as valid as they were)
        violations = check_bubbles(surfaces, only=changed)
    return surfaces, {
        "violations_found": [v.as_dict() for v in found],
        "actions": actions,
        "violations_remaining": [v.as_dict() for v in violations],
        "dropped": dropped,
    }


def check_and_repair(surfaces, projector, data, *, repair=True, iterations=20, gap=0.0, rounds=2, penalty=None):
    """The pipeline's validity step: :func:`repair_bubbles` with BFGS refits, or only the check.

    Parameters
    ----------
    surfaces : list of SubdivisionSurface
    projector : MeshProjector
        Of the fitted projections (refits).
    data : ndarray
        The fitted projections.
    repair : bool
        False: check and report only (the surfaces are returned unchanged).
    iterations : int
        BFGS iterations of each refit.
    penalty : callable, optional
        Added to the refits' objective (:func:`bubsub.clients.optimise.fit`).

    Returns
    -------
    surfaces, summary
        As :func:`repair_bubbles`; ``summary["repaired"]`` says whether repairs ran
        (and then ``unseen_parts_continued`` how many bubbles' unseen parts :func:`continued` reshaped),
        ``summary["objective_after_repair"]`` (when anything was repaired) is
        ``0.5 ||Proj(S x) - d||^2`` of the returned bubbles.
    """
    if not repair:
        found = [v.as_dict() for v in check_bubbles(surfaces)]
        return list(surfaces), {"violations_found": found, "actions": [], "violations_remaining": found,
                                "dropped": 0, "repaired": False}

    # the unseen parts first: they decide overlaps the data cannot
    before = list(surfaces)
    surfaces = [continued(x, unobserved_control(x, projector.geometry)) for x in surfaces]
    n_continued = sum(a is not b for a, b in zip(surfaces, before))

    def refit(items, changed, gone):
        # only the repaired bubbles and their neighbours, on detector windows with the rest held fixed
        return local_refit(projector, items, data, changed, iterations=iterations, touch=max(gap, 0.0) + 1e-9,
                           near=gone, penalty=penalty)[0]

    kept, summary = repair_bubbles(surfaces, refit, gap=gap, rounds=rounds)
    summary["repaired"] = True
    summary["unseen_parts_continued"] = n_continued
    if summary["actions"] and kept:
        summary["objective_after_repair"] = scene_objective(projector, kept, data)
    return kept, summary


def merged_validity(first, second, stage="after refinement"):
    """One validity summary of two :func:`check_and_repair` runs on consecutive fits.

    ``violations_found`` and ``actions`` are both runs', the second's tagged
    with ``stage``; ``violations_remaining`` and ``objective_after_repair``
    the second's; ``dropped`` the sum.
    """
    def tagged(items):
        return [dict(x, stage=stage) for x in items]

    out = dict(first)
    out.update({k: v for k, v in second.items() if k in ("violations_remaining", "objective_after_repair")})
    out["violations_found"] = first["violations_found"] + tagged(second["violations_found"])
    out["actions"] = first["actions"] + tagged(second["actions"])
    out["dropped"] = first["dropped"] + second["dropped"]
    out["repaired"] = first["repaired"] or second["repaired"]
    out["unseen_parts_continued"] = first.get("unseen_parts_continued", 0) + second.get("unseen_parts_continued", 0)
    return out
