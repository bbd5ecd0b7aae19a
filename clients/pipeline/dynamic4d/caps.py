"""Caps at the detector's top and bottom edges in a subscan: seeded where no fitted bubble explains them, and
one cap taken twice made one.

A flowing foam carries bubbles through the detector's top and bottom planes, so a warm subscan, going
backwards, meets caps its successor had no bubble for. :func:`edge_seeds` seeds them from the data's first and
last rows (:func:`unowned_discs`: the discs no fitted bubble holds as its own section) before the topology rounds;
:func:`merged_caps` makes one of two new bubbles on one cap after them, and :func:`merged_cold_caps` does the same
for the cold start's bubbles, all new. Parallel-beam 3D scans with the field-of-view model only (rows are slices
there). Also the warm detection's helpers that both stages share:
:func:`new_bubble_like` and :func:`refit_rtol`.
"""

from __future__ import annotations

import numpy as np

from bubsub.core.projection.mesh import equivalent_radius
from bubsub.clients.pipeline.inputs.fov import field_of_view, preview_extension, size_inside_fov
from bubsub.clients.pipeline.static.initial import edge_centres, edge_slices, row_pixel
from bubsub.clients.pipeline.static.preview import preview_grid
from bubsub.clients.pipeline.regions.local import (LOCAL_RTOL, Footprints, footprint, local_fits, local_refit,
                                                   others_removed, scene_residual)
from bubsub.clients.pipeline.static.topology import (merge_trial, points_inside, replace_by_one, replace_by_two,
                                                    round_bubble_maker, touching_pairs, unknowns_cost)
from bubsub.clients.pipeline.dynamic4d.tracks import edge_side, size_of

__all__ = ["LOCAL_ITERATIONS", "CAP_ITERATIONS", "edge_seeds", "unowned_discs", "disc_probes", "merged_caps",
           "merged_cold_caps", "stacked", "new_bubble_like", "refit_rtol"]

#: BFGS iterations of the local fits that compare a neighbour alone with it and an edge cap
#: (:func:`edge_seeds`), as the static topology's splits and merges.
LOCAL_ITERATIONS = 15

#: BFGS iterations of :func:`merged_caps`' fits: its one bubble starts round beside two fitted pieces (on the
#: flowing foam's first subscan, 15 left the one 0.015 above the two, 30 0.009, 60 0.007).
CAP_ITERATIONS = 30


def new_bubble_like(surfaces, geometry, settings):
    """``new_bubble(centre, radius)``: a round bubble with ``surfaces``' control mesh and attenuation (the fitted
    bubbles'), subdivided by its size (:func:`~bubsub.clients.pipeline.static.topology.round_bubble_maker` with
    ``settings``' levels)."""
    return round_bubble_maker(surfaces, geometry, surfaces[0].attenuation, settings.levels, settings.facet_pixels)


def refit_rtol(settings):
    """The convergence test of a warm subscan's refits of its changes (the preview's, the edge caps', the topology
    rounds'): the warm fit's own (``settings.warm_rtol``), never stricter than
    :data:`~bubsub.clients.pipeline.regions.local.LOCAL_RTOL`. A refit on the whole detector is held to the test
    that ended the warm fit, not to a 5 times stricter one: on the flowing foam of ``bubsub bench dynamic`` such a
    refit of 27 bubbles took 40 iterations (9 CPU seconds) to lower the scan's objective by 0.4 %, at the rate of
    the warm fit's last iterations. :func:`~bubsub.clients.pipeline.dynamic4d.detect.detect_warm` refits the new
    bubbles with the bubbles they touch to ``LOCAL_RTOL`` last: an edge cap seeded there needs its iterations."""
    return max(LOCAL_RTOL, float(settings.warm_rtol))


def edge_seeds(projector, data, surfaces, settings, voxel, residual=None):
    """Bubbles cut by the detector's top or bottom row that no fitted bubble explains, seeded and fitted.

    The data's first and last rows are reconstructed as slices
    (:func:`~bubsub.clients.pipeline.static.initial.edge_slices`, as the cold start does); each disc that is no
    fitted bubble's own section (:func:`unowned_discs`) becomes a sphere of the fitted bubbles' median radius
    beyond the edge plane with that disc as its section
    (:func:`~bubsub.clients.pipeline.static.initial.edge_centres`: a bubble that leaves through the edge later
    shows only a cap). It is kept when adding it lowers the objective or, where a neighbour's warm fit grew into
    the cap (it holds the disc, :func:`unowned_discs`) and explains too much of it for that, when the neighbour
    and the cap fitted together on a detector window beat the neighbour alone by more than the cap's unknowns
    cost and the neighbour, in that fit, gives the disc back. A neighbour that keeps the disc leaves the seed
    standing on the cap beside it, and the topology rounds' split step then cuts a piece at the cap out of the
    neighbour: two bubbles on one cap (on the second seed of ``bubsub bench dynamic``'s flowing foam, a
    spurious bubble in each of three subscans). Such a cap is left to that split step, which restarts the
    neighbour and a piece at the cap as two round bubbles.

    The seeds are then refitted with their neighbours free. The residual's discs alone miss such caps: what the
    swollen neighbour leaves of a cap a few rows deep is too faint and thin to show. Parallel-beam 3D scans only
    (rows are slices there).

    Parameters
    ----------
    projector : MeshProjector
        Of ``data``.
    data : ndarray
    surfaces : list of SubdivisionSurface
    settings : DynamicSettings
    voxel : float
        Pixel of the edge slices, mm.
    residual : ndarray float64, optional
        ``Proj(surfaces) - data`` if known, updated in place to the returned bubbles'; else computed with one
        projection.

    Returns
    -------
    list of SubdivisionSurface
        ``surfaces`` and the seeds after them.
    """
    g = projector.geometry
    if g.ndim != 3 or not surfaces or not settings.fov_model:
        return surfaces
    contrast = surfaces[0].attenuation
    residual = scene_residual(projector, surfaces, data) if residual is None else residual
    extent = preview_grid(g, voxel, preview_extension(settings.fov_model, data, contrast))[1]
    # the data's discs, as the cold start finds them: a neighbour whose warm fit grew into a cap (it has no warm
    # start of its own) explains part of its signal, and the residual's discs of what is left are too thin to show
    edges = edge_slices(data, g, contrast, extent, voxel)
    if not any(len(e[2]) for e in edges):
        return surfaces
    radius = float(np.median([equivalent_radius(size_of(s), 3) for s in surfaces]))
    new_bubble = new_bubble_like(surfaces, g, settings)
    cost = unknowns_cost(new_bubble(np.zeros(3), radius).vertices.size, residual)
    discs, holders = unowned_discs(surfaces, edges, row_pixel(g))
    # edge_centres with no bubble to account for them: every disc left becomes a sphere beyond its edge
    centres = edge_centres(np.zeros((0, 3)), np.zeros(0), discs, radius)
    probes = disc_probes(discs, row_pixel(g))
    surfaces, own, seeds = list(surfaces), Footprints(projector, surfaces), []
    for c, k, probe in zip(centres, holders, probes):
        cand = new_bubble(c, radius)
        p = footprint(projector, cand)
        if p.addition_gain(residual) < 0:
            p.add_to(residual)
            seeds.append(cand)
        elif k >= 0:
            # a neighbour's warm fit grew into the cap and explains too much of it for the seed alone to pay:
            # the neighbour alone against the two, each fitted to the data less the rest; the two only where the
            # neighbour gives the disc back (else the seed stands on the cap beside it, a second bubble once the
            # rounds split the neighbour; their split step restarts both as round bubbles instead)
            (_, f_one), (two, f_two) = local_fits(projector, [[surfaces[k]], [surfaces[k], cand]],
                                                  others_removed(residual, own[k]), LOCAL_ITERATIONS)
            if f_two < f_one - cost and not points_inside(two[0].fine(), probe[None])[0]:
                seeds.append(replace_by_two(projector, surfaces, residual, own, k, two)[0])
    if not seeds:
        return surfaces

    out, _, _ = local_refit(projector, list(surfaces) + seeds, data, range(len(surfaces), len(surfaces) + len(seeds)),
                            iterations=LOCAL_ITERATIONS, touch=radius, residual=residual, rtol=refit_rtol(settings))
    return out


def unowned_discs(surfaces, edges, row):
    """The edge discs that are no fitted bubble's own section: ``edges`` with the other discs left out.

    A disc's centre, half a row inside the edge plane, is tested against each fitted bubble that reaches the
    plane; of the discs a bubble holds, the one nearest its centre across is its own section, unless the
    bubble's centre stands further from the plane than its equivalent radius or the disc does not hold the
    bubble's centre across (a round bubble's section does; a neighbour whose warm start stood higher, or
    that grew toward a cap beside it, reaches the plane through the cap's disc: on the second seed of
    ``bubsub bench dynamic``'s flowing foam, tiny caps at the top edge were otherwise covered by their
    neighbours, two merged bubbles per subscan). A disc that no bubble holds as
    its own (a neighbour whose warm fit grew into a cap it has no warm start for, a merge the section shows
    as two discs) is unexplained.

    Parameters
    ----------
    surfaces : list of SubdivisionSurface
        3D.
    edges : list of (plane, outward, centres, radii)
        :func:`~bubsub.clients.pipeline.static.initial.edge_slices`'s.
    row : float
        A detector row's height, mm.

    Returns
    -------
    discs : list of (plane, outward, centres, radii)
    holders : list of int
        Per disc left, in order, the bubble that holds it as its second, or -1.
    """
    fines = [s.fine() for s in surfaces]
    out, holders = [], []
    for plane, outward, discs, rho in edges:
        discs, rho = np.asarray(discs, float).reshape(-1, 2), np.asarray(rho, float)
        probes = disc_probes([(plane, outward, discs, rho)], row)
        owned, holder = np.zeros(len(discs), bool), np.full(len(discs), -1)
        for k, fine in enumerate(fines):
            v = fine.vertices
            if not len(discs) or not v[:, 2].min() <= probes[0, 2] <= v[:, 2].max():
                continue
            held = np.flatnonzero(points_inside(fine, probes))
            if not len(held):
                continue
            holder[held] = k
            centre = v.mean(axis=0)
            # a bubble whose centre stands further from the plane than its radius reaches it only by growing
            # toward a cap: it holds none as its own
            if abs(centre[2] - probes[0, 2]) <= equivalent_radius(abs(fine.size), 3):
                nearest = held[np.argmin(np.linalg.norm(discs[held] - centre[:2], axis=1))]
                # a round bubble's section holds its centre across; a disc beside it is a cap it grew into
                if np.linalg.norm(discs[nearest] - centre[:2]) <= rho[nearest]:
                    owned[nearest] = True
        out.append((plane, outward, discs[~owned], rho[~owned]))
        holders += holder[~owned].tolist()
    return out, holders


def disc_probes(edges, row):
    """The points that stand for edge discs: each disc's centre half a row inside its edge plane.

    Parameters
    ----------
    edges : list of (plane, outward, centres, radii)
        :func:`~bubsub.clients.pipeline.static.initial.edge_slices`'s; ``centres`` ``(k, 2)``, mm.
    row : float
        A detector row's height, mm.

    Returns
    -------
    (n, 3) float
        mm, the discs of every plane in order.
    """
    out = [np.zeros((0, 3))]
    for plane, outward, discs, _ in edges:
        discs = np.asarray(discs, float).reshape(-1, 2)
        out.append(np.column_stack([discs, np.full(len(discs), plane - 0.5 * outward * row)]))
    return np.concatenate(out)


def stacked(larger, smaller):
    """Whether ``smaller``'s centre lies within ``larger``'s horizontal reach (the most its fine vertices stand off
    its centre across the rows' plane): one bubble above or below the other, not beside it."""
    big, small = larger.fine().vertices, smaller.fine().vertices
    c = big.mean(axis=0)
    reach = float(np.max(np.hypot(big[:, 0] - c[0], big[:, 1] - c[1])))
    offset = small.mean(axis=0)[:2] - c[:2]
    return float(np.hypot(*offset)) < reach


def merged_caps(projector, residual, ids, new_ids, after, lineage, settings, *, touch, only_stacked=False):
    """Two new bubbles on one cap at the detector's top or bottom edge, made one where one fits their data as well.

    A cap entering through an edge can be taken twice in one subscan: a seed on it (:func:`edge_seeds`) and a piece
    the split step cuts out of a neighbour whose warm fit grew into it (the bubble the neighbour then gives back).
    Both are new, side by side on one true bubble, and the warm rounds have no merge step (the static merge leaves
    bubbles at the edge alone: one bubble can stand for a cut bubble and a neighbour there). Here only pairs of
    bubbles new in the subscan (no coalescence's halves) that reach the same edge plane and touch are tried: the two
    and one round bubble of their joint size, each fitted to the data less the rest on one window for
    :data:`CAP_ITERATIONS` iterations; the one is kept when it fits less than the second bubble's unknowns worse
    (the static merge rule: two caps side by side keep the film between them, which one bubble cannot explain).
    The static merge's convexity test is not applied: a cap's shape beyond the plane is unseen, and a cap a few
    rows deep is too thin for the hull of its part in view to show a neck (a single cap of the flowing foam's
    first subscan fills 0.85-0.89 of it). The one takes the track id of the larger in view.

    Parameters
    ----------
    projector : MeshProjector
    residual : ndarray float64, ``projector.geometry.shape``
        ``Proj(after) - data``; updated in place.
    ids : sequence of int
        The successor's track ids (the warm fit's).
    new_ids, after : list
        The bubbles after the detection and their track ids.
    lineage : dict
        :func:`~bubsub.clients.pipeline.dynamic4d.tracks.assign_tracks`'s.
    settings : DynamicSettings
    touch : float
        Bubbles closer than this (mm) touch.
    only_stacked : bool
        Only pairs whose smaller bubble in view lies above or below the larger (:func:`stacked`).

    Returns
    -------
    new_ids, after : list
    lineage : dict
        Without the ``new`` entries of the ids given up.
    merged : list of dict
        ``{"id": kept, "with": given up}`` per pair made one.
    """
    g = projector.geometry
    skip = {int(i) for i in ids} | {int(i) for c in lineage["coalescences"] for i in c["children"]}
    if g.ndim != 3 or not settings.fov_model:
        return new_ids, after, lineage, []
    sides = [None if int(i) in skip else edge_side(s, g) for i, s in zip(new_ids, after)]
    fov = field_of_view(g)

    def ordered(i, j):  # the larger in view first
        return (i, j) if size_inside_fov(after[i].fine(), fov) >= size_inside_fov(after[j].fine(), fov) else (j, i)

    def tried(i, j):
        return sides[i] in ("top", "bottom") and sides[i] == sides[j] and (not only_stacked or stacked(
            *(after[k] for k in ordered(i, j))))

    pairs = touching_pairs(after, touch, tried)
    if not pairs:
        return new_ids, after, lineage, []
    after, own, merged, gone = list(after), Footprints(projector, after), [], set()
    new_bubble = new_bubble_like(after, g, settings)
    cost = unknowns_cost(new_bubble(np.zeros(3), 1.0).vertices.size, residual)
    for _, i, j in pairs:
        if i in gone or j in gone:
            continue
        (_, f_two), (one, f_one) = merge_trial(projector, after, residual, own, i, j, new_bubble, CAP_ITERATIONS)
        if f_one < f_two + cost:
            big, small = ordered(i, j)
            replace_by_one(projector, after, residual, own, big, one[0])
            own[small].add_to(residual, -1.0)
            gone.add(small)
            merged.append({"id": int(new_ids[big]), "with": int(new_ids[small])})
    if not merged:
        return new_ids, after, lineage, []
    keep = [k for k in range(len(after)) if k not in gone]
    dropped = {int(new_ids[k]) for k in gone}
    lineage = dict(lineage, new={i: why for i, why in lineage["new"].items() if int(i) not in dropped})
    return [new_ids[k] for k in keep], [after[k] for k in keep], lineage, merged


def merged_cold_caps(projector, data, surfaces, settings, *, touch):
    """The cold start's bubbles (:func:`~bubsub.clients.pipeline.reconstruct.reconstruct` of a subscan), two on one
    cap at the detector's top or bottom edge made one by :func:`merged_caps`' rule, every bubble taken as new.

    The static pipeline's merge step leaves bubbles at the field of view's edge alone, so a bubble cut by the top
    plane whose top the seeds took twice stays two there: on the cold subscan of the flowing foam's seed 0
    (``python -m bubsub.bench dynamic``), a piece of 526 voxels on the top of a bubble of 9361, carried as a
    spurious track into the next subscan. Only pairs of which one lies above or below the other are tried
    (:func:`stacked`): a cold subscan of that foam has about 70 touching pairs at its edges, 30 seconds of
    trials, and there the piece was the one pair whose smaller bubble's centre stood within the larger's
    horizontal reach (0.66 of it; the next two 0.84 and 0.95, both refused by the fits; on seed 1, one pair at
    1.1, refused). The merged bubbles are refitted with the bubbles they touch, as a warm subscan refits its new
    ones.

    Parameters
    ----------
    projector : MeshProjector
        Of ``data``.
    data : ndarray, ``projector.geometry.shape``
        The fitted projections.
    surfaces : list of SubdivisionSurface
    settings : DynamicSettings
    touch : float
        Bubbles closer than this (mm) touch.

    Returns
    -------
    surfaces : list of SubdivisionSurface
    merged : list of dict
        ``{"id": kept, "with": given up}`` per pair made one, indices into ``surfaces`` as given.
    objective : float or None
        ``0.5 ||Proj(surfaces) - data||^2`` of the surfaces returned; None when none were merged.
    """
    g = projector.geometry
    if g.ndim != 3 or not settings.fov_model or len(surfaces) < 2:
        return list(surfaces), [], None
    residual = scene_residual(projector, surfaces, data)
    ids, after, _, merged = merged_caps(projector, residual, (), list(range(len(surfaces))), list(surfaces),
                                        {"coalescences": [], "new": {}}, settings, touch=touch, only_stacked=True)
    if not merged:
        return list(surfaces), [], None
    kept = {m["id"] for m in merged}
    changed = [k for k, i in enumerate(ids) if i in kept]
    after, residual, _ = local_refit(projector, after, data, changed, iterations=max(10, settings.iterations // 2),
                                     touch=touch, residual=residual, rtol=refit_rtol(settings))
    return after, merged, 0.5 * float(np.vdot(residual, residual))
