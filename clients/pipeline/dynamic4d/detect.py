"""Detection in a warm-started subscan: bubbles its successor lacks, coalescences seen backwards, tracks that end.

``reconstruct4d`` goes backwards in time and starts each subscan from its
successor's bubbles, so a bubble that exists now but not in the successor
(it leaves through the detector's edge later, shrinks to nothing later, or
coalesces later with a neighbour) has no warm start, and a neighbour's warm
fit swells into its space. After the warm fit, :func:`detect_warm` makes
the data's voxel preview as the cold start does (:func:`data_preview`: the
same grid, its distance-transform centres) and lets its centres decide
(:func:`preview_changes`):

* **split**: a fitted bubble that holds two or more centres is replaced by
  two round bubbles at them when that lowers the objective by more than the
  second bubble's unknowns cost (a swollen neighbour, or one bubble in the
  successor that is two here), or at all when the bubble has a neck (the
  merge step's convexity test: a pair about to coalesce);
* **add**: a round bubble at each centre no fitted bubble holds, kept by the
  same rule, then refitted with its neighbours free.

Then caps at the detector's top and bottom rows that are no fitted bubble's
own section are seeded, also where a neighbour's warm fit grew into them
and gives them back when fitted with them (:func:`edge_seeds`), and the
static pipeline's topology rounds
(:func:`bubsub.clients.pipeline.static.topology.adapt_bubbles`) run on the
bubbles, with the preview and the steps :data:`WARM_STEPS`:

* **add**: the residual ``data - Proj(fit)`` is reconstructed on a coarse
  voxel grid (the field-of-view model's grid, so caps at the detector's top
  and bottom show), its blobs outside the fitted bubbles are seeded as round
  bubbles, each kept when the objective drops by more than its unknowns cost
  (the Akaike rule of the static pipeline), then refitted on a detector window
  with its neighbours free (a neighbour whose warm fit grew into its gas
  shrinks back) and the rest of the scene held fixed;
* **split**: a bubble holding two LoG blobs of the preview, or an elongated
  one (the warm fit of one bubble over two), is replaced by two when that
  lowers the objective by more than the unknowns the second bubble adds;
* **remove**: a bubble whose removal costs the objective less than its seen
  unknowns are worth goes (a bubble that left the field of view, going
  backwards, keeps only a sliver in view).

:func:`~bubsub.clients.pipeline.dynamic4d.tracks.assign_tracks` then gives every bubble its track
(continuations, coalescences seen backwards, new tracks), and a coalescence whose pair was already one bubble at
the subscan's mid-time (its film broke early in the subscan's projections) is undone
(:func:`~bubsub.clients.pipeline.dynamic4d.midtime.merged_at_midtime`): the pair then splits in the subscan before.
A new bubble that only views away from the mid-time see (one that vanished early in the subscan) goes
(:func:`~bubsub.clients.pipeline.dynamic4d.midtime.absent_at_midtime`).
"""

from __future__ import annotations

import time

import numpy as np

from bubsub.core.projection.mesh import equivalent_radius

from bubsub.clients.pipeline.inputs.fov import preview_extension
from bubsub.clients.pipeline.static.initial import (distance_centres, edge_centres, edge_slices, initial_centres,
                                                    row_pixel, small_centres)
from bubsub.clients.pipeline.regions.local import (LOCAL_RTOL, Footprints, footprint, local_fits, local_refit,
                                                   others_removed, scene_residual)
from bubsub.clients.pipeline.static.preview import (axis_pixel, preview_grid, preview_voxel_size, voxel_for_bubbles,
                                                    voxel_preview)
from bubsub.clients.pipeline.static.resolution import levels_by_size
from bubsub.clients.pipeline.static.topology import (MERGE_CONVEXITY, adapt_bubbles, add_at, points_inside,
                                                    replace_by_two, split_step, unknowns_cost)
from bubsub.core import MeshProjector
from bubsub.core.projection.subdivision import circle_surface, sphere_surface
from bubsub.clients.pipeline.dynamic4d.midtime import absent_at_midtime, merged_at_midtime
from bubsub.clients.pipeline.dynamic4d.tracks import assign_tracks, reach_of, size_of

__all__ = ["WARM_STEPS", "detect_warm", "warm_voxel", "data_preview", "preview_changes", "edge_seeds",
           "unowned_discs", "disc_probes"]

#: The topology steps of a warm subscan: no merge (a bubble that is one now and two in the successor, a split
#: forward in time, keeps the successor's two warm starts).
WARM_STEPS = ("remove", "add", "split")

#: BFGS iterations of the local fits that compare a neighbour alone with it and an edge cap
#: (:func:`edge_seeds`), as the static topology's splits and merges.
LOCAL_ITERATIONS = 15

def _new_bubble(surfaces, geometry, settings):
    """``new_bubble(centre, radius)``: a round bubble with the fitted bubbles' control mesh, subdivided by its size."""
    contrast, k = surfaces[0].attenuation, len(surfaces[0].vertices)
    if surfaces[0].ndim == 2:
        return lambda c, r: circle_surface(c, r, contrast, control=k, levels=surfaces[0].levels)
    k = k if k in (12, 42, 162) else 42
    return lambda c, r: levels_by_size([sphere_surface(c, r, contrast, control=k, levels=settings.levels)], geometry,
                                       settings.levels, settings.facet_pixels)[0]


def edge_seeds(projector, data, surfaces, settings, voxel):
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

    Returns
    -------
    list of SubdivisionSurface
        ``surfaces`` and the seeds after them.
    """
    g = projector.geometry
    if g.ndim != 3 or not surfaces or not settings.fov_model:
        return surfaces
    contrast = surfaces[0].attenuation
    residual = scene_residual(projector, surfaces, data)
    extent = preview_grid(g, voxel, preview_extension(settings.fov_model, data, contrast))[1]
    # the data's discs, as the cold start finds them: a neighbour whose warm fit grew into a cap (it has no warm
    # start of its own) explains part of its signal, and the residual's discs of what is left are too thin to show
    edges = edge_slices(data, g, contrast, extent, voxel)
    if not any(len(e[2]) for e in edges):
        return surfaces
    radius = float(np.median([equivalent_radius(size_of(s), 3) for s in surfaces]))
    new_bubble = _new_bubble(surfaces, g, settings)
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
                            iterations=LOCAL_ITERATIONS, touch=radius, residual=residual, rtol=_refit_rtol(settings))
    return out


def _refit_rtol(settings):
    """The convergence test of a warm subscan's refits of its changes (the preview's, the edge caps', the topology
    rounds'): the warm fit's own (``settings.warm_rtol``), never stricter than
    :data:`~bubsub.clients.pipeline.regions.local.LOCAL_RTOL`. A refit on the whole detector is held to the test
    that ended the warm fit, not to a 5 times stricter one: on the flowing foam of ``bubsub bench dynamic`` such a
    refit of 27 bubbles took 40 iterations (9 CPU seconds) to lower the scan's objective by 0.4 %, at the rate of
    the warm fit's last iterations. :func:`detect_warm` refits the new bubbles with the bubbles they touch to
    ``LOCAL_RTOL`` last: an edge cap seeded there needs its iterations."""
    return max(LOCAL_RTOL, float(settings.warm_rtol))


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


def warm_voxel(geometry, data, contrast, settings, surfaces):
    """The voxel of a warm subscan's previews (mm): ``settings.voxel_size``, else the cold start's default made
    finer when the fitted bubbles are few voxels across
    (:func:`~bubsub.clients.pipeline.static.preview.voxel_for_bubbles`), never finer than a detector pixel at the
    axis (a small detector's default voxel is a fraction of one; the residual preview runs on twice this voxel and
    a bubble added is at least 3 voxels in radius, so a finer grid costs a warm subscan more than its fit)."""
    if settings.voxel_size is not None:
        return settings.voxel_size
    default = preview_voxel_size(geometry)
    voxel = voxel_for_bubbles([equivalent_radius(size_of(s), s.ndim) for s in surfaces], geometry, default,
                              preview_extension(settings.fov_model, data, contrast)) or default
    return max(voxel, axis_pixel(geometry))


def data_preview(geometry, data, contrast, settings, voxel):
    """The voxel preview of a warm subscan's data, as the cold start makes it, and the bubble centres in it.

    The grid is the cold start's (:func:`~bubsub.clients.pipeline.static.preview.preview_grid` at ``voxel``,
    :func:`warm_voxel`'s; widened by the field-of-view model, so that caps at the detector's edge show); the centres are the cold start's ``"dt"`` detector (the distance transform's maxima of the Otsu mask)
    and, in 3D, the small bubbles its opening erased (:func:`~bubsub.clients.pipeline.static.initial.small_centres`).

    Parameters
    ----------
    geometry : ScanGeometry
    data : ndarray, ``geometry.shape``
    contrast : float
    settings : DynamicSettings
    voxel : float
        mm (:func:`warm_voxel`).

    Returns
    -------
    image : ndarray float32, ``(slices, rows, cols)`` or ``(rows, cols)``
    extent : tuple
        mm.
    centres : (k, ndim) float
        mm, largest distance first.
    radii : (k,) float
        mm: the distance transform at each centre (a small bubble's blob radius).
    """
    extend = preview_extension(settings.fov_model, data, contrast)
    image, extent = voxel_preview(data, geometry, contrast, voxel, method=settings.preview, extend=extend)
    edge = not settings.fov_model
    if image.ndim == 3:
        centres, radii, mask = distance_centres(image, extent, min_distance=settings.min_distance,
                                                border_is_background=edge)
        small = small_centres(image, extent, contrast, mask)
        centres, radii = np.concatenate([centres, small[0]]), np.concatenate([radii, small[1]])
    else:
        centres, radii = initial_centres(image, extent, detector="dt", min_distance=settings.min_distance,
                                         border_is_background=edge)
    order = np.argsort(-np.asarray(radii), kind="stable")
    return image, extent, np.asarray(centres, float).reshape(-1, image.ndim)[order], np.asarray(radii, float)[order]


def preview_changes(projector, surfaces, data, centres, radii, settings, *, min_radius):
    """Splits and additions that the data preview's bubble centres call for, each kept by the static rule.

    * **split**: a fitted bubble that holds two or more centres (a neighbour whose warm fit grew over a bubble
      the successor lacks, or one bubble in the successor that is two here) is replaced by two round bubbles at
      its two largest centres, fitted locally, kept when the objective drops by more than the unknowns the
      second bubble adds, or by anything when the bubble has a neck (convexity below
      :data:`~bubsub.clients.pipeline.static.topology.MERGE_CONVEXITY`, the merge step's test) and lies inside
      the field of view (:func:`~bubsub.clients.pipeline.static.topology.split_step`): a pair about to
      coalesce, one bubble in the successor, differs from one bubble by little more than its thin film;
    * **add**: a round bubble at each centre that no bubble holds, its radius cut to the gap to its neighbours,
      kept when the objective drops by more than its unknowns cost
      (:func:`~bubsub.clients.pipeline.static.topology.add_at`).

    The bubbles changed are then refitted on detector windows with their neighbours (within their own size)
    free and the rest of the scene fixed: a neighbour whose warm fit took a new bubble's space gives it back.

    Parameters
    ----------
    projector : MeshProjector
    surfaces : list of SubdivisionSurface
        The warm fit.
    data : ndarray
    centres : (k, ndim) float
    radii : (k,) float
        :func:`data_preview`'s, mm.
    settings : DynamicSettings
    min_radius : float
        Smallest bubble added, mm.

    Returns
    -------
    surfaces : list of SubdivisionSurface
    changes : list of dict
        As :func:`~bubsub.clients.pipeline.static.topology.adapt_topology`'s, kinds ``preview_split`` and ``preview_add``.
    """
    surfaces = list(surfaces)
    if not surfaces or not len(centres):
        return surfaces, []
    new_bubble = _new_bubble(surfaces, projector.geometry, settings)
    own = Footprints(projector, surfaces)
    residual = scene_residual(projector, surfaces, data)
    cost = unknowns_cost(new_bubble(np.zeros(surfaces[0].ndim), 1.0).vertices.size, residual)
    changes = []
    held = np.array([points_inside(s.fine(), centres) for s in surfaces])
    twice = {k for k in range(len(surfaces)) if held[k].sum() >= 2}
    start = {id(s) for s in surfaces}
    iterations = max(10, settings.iterations // 2)
    if twice:
        surfaces, own = split_step(projector, surfaces, residual, own, data, new_bubble, changes, 0,
                                   ratio=np.inf, iterations=15, max_tries=len(twice), cost=cost,
                                   blobs=(centres, radii), only=twice, neck_convexity=MERGE_CONVEXITY)
    free = ~held.any(axis=0)
    if np.any(free):
        surfaces, own = add_at(projector, surfaces, residual, own, centres[free], radii[free], new_bubble, changes, 0,
                               min_radius=min_radius, max_add=int(free.sum()), cost=cost)
    for c in changes:
        c["change"] = "preview_" + c["change"]
    changed = [k for k, s in enumerate(surfaces) if id(s) not in start]
    if changed:
        surfaces, _, _ = local_refit(projector, surfaces, data, changed, iterations=iterations,
                                     touch=max(reach_of(surfaces[k]) for k in changed), residual=residual,
                                     rtol=_refit_rtol(settings))
    return surfaces, changes


def detect_warm(geometry, data, ids, surfaces, settings, *, successor_sizes, next_id):
    """The warm fit's bubbles after the topology rounds of :data:`WARM_STEPS`, with their track ids.

    Parameters
    ----------
    geometry : ScanGeometry
        Of the fitted projections.
    data : ndarray, ``geometry.shape``
        The fitted projections' bubble signal.
    ids : sequence of int
        Track ids of ``surfaces``.
    surfaces : list of SubdivisionSurface
        The warm fit.
    settings : DynamicSettings
        Its static settings decide the rounds (``topology_rounds``, ``iterations``, ``fov_model``, ...).
    successor_sizes : dict
        ``id -> size`` of each track in the successor (mm^2 or mm^3).
    next_id : int
        The first unused track id.

    Returns
    -------
    ids : list of int
    surfaces : list of SubdivisionSurface
    lineage : dict
        See :func:`assign_tracks`.
    summary : dict
        The rounds' ``changes`` counted by kind, ``rounds``, ``objective``, ``voxel_mm`` (of the residual preview),
        ``preview`` (the data preview's ``voxel_mm``, ``shape`` and ``centres``), ``seconds`` (wall seconds of
        the data preview, its splits and additions, the edge caps, the rounds, the tracks with the new bubbles'
        refit).
    next_id : int
    """
    surfaces = list(surfaces)
    if not surfaces or settings.topology_rounds < 1:
        return list(ids), surfaces, {"new": {}, "coalescences": [], "removed": {}}, {"rounds": 0, "objective": None}, \
            next_id
    contrast = surfaces[0].attenuation
    voxel = warm_voxel(geometry, data, contrast, settings, surfaces)
    projector = MeshProjector(geometry, supersampling=settings.supersampling)
    t0 = time.perf_counter()
    image, extent, centres, radii = data_preview(geometry, data, contrast, settings, voxel)
    seconds_preview = time.perf_counter() - t0
    preview_voxel = (extent[1] - extent[0]) / image.shape[-1]
    previewed, preview_log = preview_changes(projector, surfaces, data, centres, radii, settings,
                                             min_radius=1.5 * preview_voxel)
    seconds = {"preview": seconds_preview, "preview_changes": time.perf_counter() - t0 - seconds_preview}
    t0 = time.perf_counter()
    # caps at the detector's top and bottom: the rounds' remove step then judges them by the static rule
    seeded = edge_seeds(projector, data, previewed, settings, voxel)
    seconds["edge_seeds"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    after, summary = adapt_bubbles(projector, seeded, data,
                                   contrast=contrast, voxel=voxel, rounds=settings.topology_rounds,
                                   iterations=settings.iterations, levels=settings.levels,
                                   facet_pixels=settings.facet_pixels, voxel_size=settings.voxel_size,
                                   method=settings.preview, fov_model=settings.fov_model, image=image, extent=extent,
                                   progress=settings.progress, steps=WARM_STEPS, unexplained_only=True,
                                   refit_rtol=_refit_rtol(settings), after_removals=False)
    seconds["rounds"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    summary["changes"] = preview_log + summary["changes"]
    new_ids, lineage, next_id = assign_tracks(ids, surfaces, after, successor_sizes, geometry, next_id)
    # a pair that coalesced before the subscan's mid-time is one bubble here: the warm fit's, refitted below;
    # a bubble that only views away from the mid-time see is none
    residual = scene_residual(projector, after, data)
    new_ids, after, lineage, undone = merged_at_midtime(projector, residual, ids, surfaces, new_ids, after, lineage)
    new_ids, after, lineage, absent = absent_at_midtime(projector, residual, ids, new_ids, after, lineage)
    known, parents = set(ids), {u["parent"] for u in undone}
    born = [k for k, i in enumerate(new_ids) if i not in known]
    restored = [k for k, i in enumerate(new_ids) if i in parents]
    if born or restored:
        changed = born + restored
        # the new bubbles (and a pair's bubble restored) with every neighbour within their size free: a
        # neighbour whose warm fit grew into a new bubble's gas (the rounds refit only bubbles within a few
        # voxels) gives it back; that refit of many bubbles stops at the warm fit's test, then the new bubbles
        # and the bubbles they touch go on to LOCAL_RTOL (an edge cap seeded here needs its iterations): on
        # subscans 7 and 6 of the flowing foam the same bubbles found, missed and merged as one refit of all to
        # LOCAL_RTOL, for half its CPU seconds
        iterations = max(10, settings.iterations // 2)
        after, residual, _ = local_refit(projector, after, data, changed, iterations=iterations,
                                         touch=2 * max(reach_of(after[k]) for k in changed), residual=residual,
                                         rtol=_refit_rtol(settings))
        after, residual, _ = local_refit(projector, after, data, changed, iterations=iterations, touch=0.0,
                                         residual=residual)
    if born or restored or absent:
        summary["objective"] = 0.5 * float(np.vdot(residual, residual))
    seconds["tracks_and_refit"] = time.perf_counter() - t0
    counts = {}
    for c in summary["changes"]:
        counts[c["change"]] = counts.get(c["change"], 0) + 1
    counts["edge_seed"] = len(seeded) - len(previewed)
    if undone:
        counts["coalescence_before_midtime"] = len(undone)
    if absent:
        counts["absent_at_midtime"] = len(absent)
    return new_ids, after, lineage, {"rounds": summary["rounds"], "changes": counts,
                                     "objective": summary["objective"], "voxel_mm": voxel,
                                     "preview": {"voxel_mm": preview_voxel, "shape": list(image.shape),
                                                 "centres": len(centres)},
                                     "seconds": seconds}, next_id
