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
and gives them back when fitted with them (:func:`~bubsub.clients.pipeline.dynamic4d.caps.edge_seeds`), and the
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
(:func:`~bubsub.clients.pipeline.dynamic4d.midtime.absent_at_midtime`), and two new bubbles on one cap at the
detector's edge are made one where one fits their data as well
(:func:`~bubsub.clients.pipeline.dynamic4d.caps.merged_caps`).
"""

from __future__ import annotations

import time

import numpy as np

from bubsub.core.projection.mesh import equivalent_radius

from bubsub.clients.pipeline.inputs.fov import preview_extension
from bubsub.clients.pipeline.static.initial import distance_centres, initial_centres, small_centres
from bubsub.clients.pipeline.regions.local import Footprints, local_refit, scene_residual
from bubsub.clients.pipeline.static.preview import axis_pixel, preview_voxel_size, voxel_for_bubbles, voxel_preview
from bubsub.clients.pipeline.static.topology import (MERGE_CONVEXITY, adapt_bubbles, add_at, points_inside,
                                                    split_step, unknowns_cost)
from bubsub.core import MeshProjector
from bubsub.core.malloc import release_free_memory
from bubsub.core.projection.backends.raster import release_stores
from bubsub.clients.pipeline.dynamic4d.caps import edge_seeds, merged_caps, new_bubble_like, refit_rtol
from bubsub.clients.pipeline.dynamic4d.midtime import absent_at_midtime, merged_at_midtime
from bubsub.clients.pipeline.dynamic4d.tracks import assign_tracks, reach_of, size_of

__all__ = ["WARM_STEPS", "detect_warm", "warm_voxel", "data_preview", "preview_changes"]

#: The topology steps of a warm subscan: no merge (a bubble that is one now and two in the successor, a split
#: forward in time, keeps the successor's two warm starts).
WARM_STEPS = ("remove", "add", "split")


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
    residual : ndarray float64, ``data.shape``
        ``Proj(surfaces) - data`` of the returned bubbles.
    """
    surfaces = list(surfaces)
    residual = scene_residual(projector, surfaces, data)
    if not surfaces or not len(centres):
        return surfaces, [], residual
    new_bubble = new_bubble_like(surfaces, projector.geometry, settings)
    own = Footprints(projector, surfaces)
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
        surfaces, residual, _ = local_refit(projector, surfaces, data, changed, iterations=iterations,
                                            touch=max(reach_of(surfaces[k]) for k in changed), residual=residual,
                                            rtol=refit_rtol(settings))
    return surfaces, changes, residual


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
    # one residual, kept up to date by each step in turn (each scene projection is a third of a second)
    previewed, preview_log, residual = preview_changes(projector, surfaces, data, centres, radii, settings,
                                                       min_radius=1.5 * preview_voxel)
    seconds = {"preview": seconds_preview, "preview_changes": time.perf_counter() - t0 - seconds_preview}
    t0 = time.perf_counter()
    # caps at the detector's top and bottom: the rounds' remove step then judges them by the static rule
    seeded = edge_seeds(projector, data, previewed, settings, voxel, residual=residual)
    seconds["edge_seeds"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    after, summary = adapt_bubbles(projector, seeded, data,
                                   contrast=contrast, voxel=voxel, rounds=settings.topology_rounds,
                                   iterations=settings.iterations, levels=settings.levels,
                                   facet_pixels=settings.facet_pixels, voxel_size=settings.voxel_size,
                                   method=settings.preview, fov_model=settings.fov_model, image=image, extent=extent,
                                   progress=settings.progress, steps=WARM_STEPS, unexplained_only=True,
                                   refit_rtol=refit_rtol(settings), after_removals=False, residual=residual)
    seconds["rounds"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    summary["changes"] = preview_log + summary["changes"]
    new_ids, lineage, next_id = assign_tracks(ids, surfaces, after, successor_sizes, geometry, next_id)
    # a pair that coalesced before the subscan's mid-time is one bubble here: the warm fit's, refitted below;
    # a bubble that only views away from the mid-time see is none (the residual is the rounds' result's: they
    # kept it up to date in place)
    new_ids, after, lineage, undone = merged_at_midtime(projector, residual, ids, surfaces, new_ids, after, lineage)
    new_ids, after, lineage, absent = absent_at_midtime(projector, residual, ids, new_ids, after, lineage)
    new_ids, after, lineage, caps = merged_caps(projector, residual, ids, new_ids, after, lineage, settings,
                                                touch=2 * voxel)
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
        # the detection's fits' crossing stores and freed arrays given back first: this refit can take most of the
        # subscan's bubbles on the whole detector, the warm subscan's peak memory
        release_stores()
        release_free_memory()
        after, residual, _ = local_refit(projector, after, data, changed, iterations=iterations,
                                         touch=2 * max(reach_of(after[k]) for k in changed), residual=residual,
                                         rtol=refit_rtol(settings))
        after, residual, _ = local_refit(projector, after, data, changed, iterations=iterations, touch=0.0,
                                         residual=residual)
    if born or restored or absent or caps:
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
    if caps:
        counts["caps_merged"] = len(caps)
    return new_ids, after, lineage, {"rounds": summary["rounds"], "changes": counts,
                                     "objective": summary["objective"], "voxel_mm": voxel,
                                     "preview": {"voxel_mm": preview_voxel, "shape": list(image.shape),
                                                 "centres": len(centres)},
                                     "seconds": seconds}, next_id
