"""The BubSub reconstruction pipeline: scan file in, one mesh per bubble out.

1. Low-resolution voxel reconstruction of the bubble data, the preview
   (:mod:`.preview`; box-constrained projected gradient by default).
2. Bubble centres: Laplacian-of-Gaussian blobs or distance-transform maxima of the
   Otsu mask, in 2D whichever explains the data better (:mod:`.initial`).
3. One spherical control mesh per bubble with a constant radius, optionally
   improved by a radius-only fit (paper eq. 4-5), or a user-given initial mesh.
4. BFGS on all control vertices, coarse to fine in the data: binned pixels
   first, the full detector last, each level ended on convergence
   (:mod:`bubsub.clients.optimise.levels`); topology rounds (:mod:`.topology`)
   and the validity check and repair (:mod:`.repair`), each refitting only the
   bubbles it changed on detector windows (:mod:`.local`); one coarse-to-fine
   step in the control meshes, kept when it explains the data better
   (:mod:`.refine`), and its check and repair. A tall parallel-beam scan is
   reconstructed slab by slab of detector rows (:mod:`.slabs`).
5. Outputs, each written atomically: ``bubbles.ply`` (3D) or ``bubbles.json``
   (2D), ``bubbles.csv`` (+ ``bubbles.csv-metadata.json``), ``report.json``,
   ``overlay.png``, ``sizes.png`` and (3D) ``meshes.png``
   (:func:`bubsub.clients.pipeline.outputs.write_outputs`, pictures by
   :mod:`bubsub.clients.pipeline.figures`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from bubsub.core import MeshProjector, ScanGeometry
from bubsub.core.io.meshio import read_ply, read_polygons_json
from bubsub.core.malloc import release_free_memory
from bubsub.core.metrics import projection_mse
from bubsub.core.projection.mesh import equivalent_radius
from bubsub.core.projection.subdivision import SubdivisionSurface

from bubsub.clients.optimise.fit import estimate_radii
from bubsub.clients.optimise.levels import bin_factors, coarse_surfaces, fit_levels
from bubsub.clients.pipeline.checks import check_bubble_signal, check_settings
from bubsub.clients.pipeline.fov import (field_of_view, fov_report, inside_fov, preview_extension, size_inside_fov,
                                         unobserved_control)
from bubsub.clients.pipeline.initial import choose_initial, default_detector
from bubsub.clients.pipeline.local import scene_objective
from bubsub.clients.pipeline.preview import preview_voxel_size, voxel_for_bubbles, voxel_preview
from bubsub.clients.pipeline.refine import can_refine, coarse_rate, control_counts, refine_and_check
from bubsub.clients.pipeline.repair import check_and_repair, merged_validity
from bubsub.clients.pipeline.resolution import level_counts, levels_by_size
from bubsub.clients.pipeline.topology import adapt_bubbles

__all__ = ["ReconstructionSettings", "Reconstruction", "reconstruct", "load_initial", "split_holdout", "prune",
           "seen_slab", "settings_preview", "settings_initial", "coarse_radii", "initial_bubbles", "projector_report",
           "merged_projector_report", "REMOTE_PHASES"]


@dataclass
class ReconstructionSettings:
    """What ``bubsub reconstruct`` can be told (defaults follow the paper)."""

    iterations: int = 80  # the full detector's cap, 3x on binned levels (.optimise.levels); a level ends earlier on convergence
    data_levels: int | None = None  # fit on 2^(k-1)-binned, ..., full pixels; default 2 for 3D detectors >= 96 px
    fit_rtol: float | None = 2e-4  # converged: objective down by < fit_rtol x itself over 5 iterations
    control_points: int | None = None  # 42 in 3D, 9 in 2D; a kept refinement delivers 162 (3D) or twice (2D)
    levels: int = 2  # the most Loop levels; in 3D each bubble takes as few as keep its faces within facet_pixels
    facet_pixels: float = 0.2  # .resolution: most a fine face may stand from a sphere of its bubble's size; 0: all at levels
    radius: float | None = None  # initial radius (mm); default: median from the distance transform
    estimate_radii: bool = True
    supersampling: int = 1
    holdout: str | None = None  # "odd" or "even": projections kept aside for validation
    voxel_size: float | None = None  # of the initial voxel reconstruction; default: from the field of view
    min_distance: float | None = None  # between bubble centres (mm)
    background_subtracted: bool = False  # accept a positive contrast without /exchange/background
    progress: bool = True
    preview: str = "box"  # voxel preview: "box" (0 <= x <= |contrast|, BB steps) or "sirt" (x >= 0)
    detector: str | None = None  # initial centres: "auto", "log" or "dt" (see .initial); default "auto" in 2D, "dt" in 3D
    topology: bool = True  # add/remove/merge/split bubbles between fits when the objective says so (see .topology)
    topology_rounds: int = 2
    repair: bool = True  # round self-intersecting bubbles, separate overlapping ones, refit (see .repair)
    repair_iterations: int = 20  # BFGS iterations of each refit after a repair
    fov_model: bool = True  # preview beyond the field of view, cut bubbles seeded at their edge (see .fov)
    # strength of the penalty keeping bubbles a film apart during the fits (.optimise.separation); off by
    # default: at 1 the dense 2D foam's DDI went from 0.010 to 0.077 (docs/robustness.md)
    separation: float = 0.0
    # coarse-to-fine: after the repair, refine each control mesh once and refit (then check and repair
    # again); kept when the Akaike score improves (.refine; bubbles from the preview only, not from --init)
    refine: bool = True
    refine_iterations: int = 80  # of the refined fit (it stops after 10 unless the refinement pays for itself)


@dataclass
class Reconstruction:
    """Result of :func:`reconstruct`."""

    surfaces: list
    report: dict
    preview: np.ndarray | None = None
    preview_extent: tuple | None = None
    files: dict = field(default_factory=dict)
    ids: list | None = None  # bubble ids written to the outputs (default 0..n-1); track ids in 4D


def load_initial(path, contrast, levels=2):
    """Initial control meshes from a previous reconstruction (``bubbles.ply`` or ``bubbles.json``)."""
    path = Path(path)
    if path.suffix.lower() == ".ply":
        items = read_ply(path, attenuation=contrast)
    elif path.suffix.lower() == ".json":
        items = read_polygons_json(path, attenuation=contrast)
    else:
        raise ValueError(f"initial mesh {path} must be a .ply (3D) or .json (2D) file")
    return [SubdivisionSurface(m, levels) for m in items]


def split_holdout(geometry, data, holdout):
    """The projections to fit and those held out for validation (``--holdout``).

    Parameters
    ----------
    geometry : bubsub.core.ScanGeometry
    data : ndarray, ``(angles, ...)``
    holdout : {None, "odd", "even"}
        Which projections (by index) are held out; None holds out none.

    Returns
    -------
    fit_geometry, fit_data, held_geometry, held_data
        The last two None when nothing is held out.
    """
    if holdout is None:
        return geometry, data, None, None
    if holdout not in ("odd", "even"):
        raise ValueError(f"holdout must be 'odd' or 'even', got {holdout!r}")
    keep = slice(0, None, 2) if holdout == "odd" else slice(1, None, 2)
    rest = slice(1, None, 2) if holdout == "odd" else slice(0, None, 2)
    if geometry.n_angles < 2:
        raise ValueError("holding out projections needs at least two of them")
    return geometry[keep], data[keep], geometry[rest], data[rest]


def reconstruct(scan, settings=None, *, init=None, projector_factory=None):
    """Reconstruct the bubbles of a scan.

    Parameters
    ----------
    scan : bubsub.core.io.scanfile.Scan
    settings : ReconstructionSettings, optional
    init : list of SubdivisionSurface, optional
        Initial bubbles (e.g. :func:`load_initial` of a previous frame);
        skips the voxel-based initialisation.
    projector_factory : callable(geometry, data, surfaces) -> projector, optional
        Makes the object :func:`fit` calls, holding ``data``; by default a
        local :class:`MeshProjector`. ``bubsub reconstruct --server`` passes
        one that creates a remote job with the surfaces' topology.

    Returns
    -------
    Reconstruction
    """
    s = settings or ReconstructionSettings()
    check_settings(s, scan.ndim)
    check_bubble_signal(scan, background_subtracted=s.background_subtracted)
    t0 = time.perf_counter()
    clock = _PhaseClock()
    contrast = scan.bubble_contrast
    data = scan.bubble_data
    geometry = scan.geometry
    g_fit, d_fit, g_val, d_val = split_holdout(geometry, data, s.holdout)

    local = MeshProjector(g_fit, supersampling=s.supersampling)
    detector, initialisation = default_detector(s.detector, g_fit.ndim), None
    if init is None:
        surfaces, initialisation, image, extent, finer = initial_bubbles(d_fit, g_fit, contrast, local, s, clock=clock)
    else:
        surfaces = [x.with_attenuation(contrast) for x in init]
        finer = _finer_voxel(s, surfaces, g_fit, d_fit, contrast)
        image, extent = settings_preview(d_fit, g_fit, contrast, replace(s, voxel_size=finer or s.voxel_size))
        clock.mark("preview")
    t_init = time.perf_counter() - t0
    clock.mark("initial_bubbles")
    factors = bin_factors(g_fit, s.data_levels)
    if s.estimate_radii and init is None and detector != "auto":
        surfaces = coarse_radii(surfaces, g_fit, d_fit, factors[0], s)
    surfaces = levels_by_size(surfaces, g_fit, s.levels, s.facet_pixels)  # as finely as its size needs (3D)
    clock.mark("radius_estimation")
    if projector_factory is None:
        projector, fit_data = local, d_fit
    else:  # a remote job holds its surfaces' topology and levels: made once they are known
        projector = projector_factory(g_fit, d_fit, surfaces)
        fit_data = None
    voxel = (extent[1] - extent[0]) / image.shape[-1]
    penalty = _separation(s, d_fit, len(surfaces), voxel) if fit_data is not None else None
    # the objective of the initial bubbles on the full detector (the levels' own objectives are on their pixels)
    f_start = float((projector.objective(surfaces, fit_data) if fit_data is not None
                     else projector.objective(surfaces))[0])
    result, fit_levels_report = fit_levels(projector, surfaces, d_fit, factors=factors, iterations=s.iterations,
                                           rtol=s.fit_rtol, penalty=penalty, progress=s.progress,
                                           factory=projector_factory)
    clock.mark("fit")
    kept, dropped = prune(result.surfaces, min_radius=voxel)
    topology = refinement = None
    interrupted = result.interrupted  # Ctrl-C: no further changes, write what we have
    checker = local
    try:
        if s.topology and s.topology_rounds > 0 and kept and not interrupted:
            kept, topology = adapt_bubbles(kept, g_fit, d_fit, contrast, image, extent, voxel, s, penalty=penalty)
        clock.mark("topology")

        def checked(items):
            return check_and_repair(items, checker, d_fit, repair=s.repair and not interrupted,
                                    iterations=s.repair_iterations, gap=0.25 * voxel, penalty=penalty)

        will_refine = s.refine and init is None and not interrupted
        # the coarse bubbles' data term before the repair: the refinement's trial discounts the repair's rise in it
        reached = None
        if will_refine and kept:
            reached = topology["objective"] if topology else scene_objective(local, kept, d_fit)
        kept, validity = checked(kept)
        clock.mark("validity")
        if will_refine and can_refine(kept):
            # after the repair, so the refined fit also fills the gas of dropped bubbles; checked again
            kept, refinement, again = refine_and_check(local, kept, d_fit, checked, iterations=s.refine_iterations,
                                                       penalty=penalty, progress=s.progress, rtol=s.fit_rtol,
                                                       coarse_rate=coarse_rate(result.history), reached=reached)
            if again is not None:
                validity = merged_validity(validity, again)
        clock.mark("refine")
        edge = seen_slab(g_fit)
        if edge is not None:  # slivers at the detector's edge, once every change is made
            kept, late = prune(kept, min_radius=voxel, fov=edge)
            dropped += late
            clock.mark("edge_slivers")
    except KeyboardInterrupt:  # in the topology rounds, the repair or the refinement: report the bubbles as they were
        interrupted = True
        kept, validity = check_and_repair(kept, checker, d_fit, repair=False)
        clock.mark("validity")

    refined = bool(refinement and refinement["kept"])
    # what was delivered: the bubbles written, after the topology rounds, the repair and a kept refined fit
    try:
        f_final = scene_objective(local, kept, d_fit)
    except KeyboardInterrupt:  # a second Ctrl-C: the outputs matter more than this figure
        f_final, interrupted = None, True
    report = {
        "bubbles": len(kept),
        "bubbles_initial": len(surfaces),
        "initialisation": initialisation,
        # the voxel preview's grid; made finer for bubbles a few voxels across (.preview.voxel_for_bubbles)
        "preview": {"voxel_mm": voxel, "shape": list(image.shape), "finer_for_bubbles": finer is not None},
        "bubbles_dropped": dropped + validity["dropped"],
        "validity": validity,
        "topology": topology,
        "refinement": refinement,
        "dimension": geometry.ndim,
        # the fits that made the delivered bubbles: the fit, then the refined fit when it was kept
        "iterations": result.iterations + (refinement["iterations"] if refined else 0),
        "evaluations": result.evaluations + (refinement["evaluations"] if refined else 0),
        "delivered_fit": "refined fit" if refined else "fit",
        "fit": {"objective": result.objective, "iterations": result.iterations, "evaluations": result.evaluations,
                "stop_reason": result.stop_reason, "seconds": result.seconds, "penalty": result.penalty},
        "fit_levels": fit_levels_report,
        # 0.5 ||Proj(S x) - d||^2 of the delivered bubbles on the fitted projections, as initial_objective
        "final_objective": f_final,
        "initial_objective": f_start,
        "method": result.method,
        "interrupted": interrupted,
        "stop_reason": "interrupted" if interrupted else (refinement["stop_reason"] if refined
                                                          else result.stop_reason),
        "seconds_total": time.perf_counter() - t0,
        "seconds_fit": result.seconds,
        "seconds_initialisation": t_init,
        "projections_used": g_fit.n_angles,
        "holdout": s.holdout,
        "field_of_view_mm": fov_report(geometry),
        "unobserved_control_vertices": [int(unobserved_control(x, g_fit).sum()) for x in kept],
        # bubbles per subdivision level (.resolution; the refinement moves one level into the control meshes)
        "subdivision_levels": level_counts(kept),
        # bubbles per number of control points (2D) or vertices (3D); a kept refinement doubles (2D) or about
        # quadruples (3D) them
        "control_points": control_counts(kept),
        "settings": {k: v for k, v in s.__dict__.items() if k != "progress"},
    }
    if g_val is not None:
        pred = MeshProjector(g_val, supersampling=s.supersampling).forward(kept)
        report["holdout_projections"] = g_val.n_angles
        report["holdout_mse"] = projection_mse(pred, d_val)
        clock.mark("holdout")
    # wall and CPU seconds of each phase (CPU: this process, all threads)
    report["seconds_parts"], report["cpu_seconds_parts"] = clock.parts()
    report["projector"] = projector_report(projector if projector_factory is not None else None,
                                           report["seconds_parts"], local.backend)
    return Reconstruction(kept, report, image, extent)


#: the phases of :func:`reconstruct` that project through ``projector_factory``'s projectors (the initial
#: objective and every level of the fit); the others project with local ones
REMOTE_PHASES = ("fit",)


def projector_report(remote, phases, backend):
    """``report.json``'s ``projector``: where the projections of each phase ran.

    Parameters
    ----------
    remote : object or None
        The projector ``projector_factory`` made (a
        :class:`~bubsub.clients.remote.client.RemoteJob` says its ``server``); None when every
        phase projected locally.
    phases : iterable of str
        The phases that ran, in order (``seconds_parts``' keys).
    backend : str
        The local projectors' backend.

    Returns
    -------
    dict
        ``server`` (URL or None), ``remote_phases``, ``local_phases`` (lists of phase names) and
        ``local_backend``.
    """
    phases = list(phases)
    remote_phases = [p for p in phases if p in REMOTE_PHASES] if remote is not None else []
    return {"server": getattr(remote, "server", None) if remote is not None else None,
            "remote_phases": remote_phases, "local_phases": [p for p in phases if p not in remote_phases],
            "local_backend": backend}


def merged_projector_report(reports):
    """One :func:`projector_report` for several runs' (the slabs of a scan): the first server named, and
    the phases that ran remotely in any run, or locally in any, in the order they first appear; None
    when no run has one."""
    reports = [r for r in reports if r]
    if not reports:
        return None
    remote, local = [], []
    for r in reports:
        remote += [p for p in r["remote_phases"] if p not in remote]
        local += [p for p in r["local_phases"] if p not in local]
    return {"server": next((r["server"] for r in reports if r["server"]), None), "remote_phases": remote,
            "local_phases": local, "local_backend": reports[0]["local_backend"]}


def initial_bubbles(data, geometry, contrast, projector, settings, *, clock=None):
    """The pipeline's initial bubbles from its voxel preview of ``data`` (bubbles positive).

    :func:`settings_preview` and :func:`settings_initial`, then, when the
    seeds are a few voxels across (:func:`voxel_for_bubbles`), both again on
    a finer preview.

    Parameters
    ----------
    data : ndarray, ``(angles, rows, cols)`` or ``(angles, cols)``
    geometry : ScanGeometry
        Of ``data``.
    contrast : float
    projector : MeshProjector
        Of ``data`` (local).
    settings : ReconstructionSettings
    clock : optional
        The pipeline's phase clock (``preview`` and ``initial_bubbles`` marked).

    Returns
    -------
    surfaces : list of SubdivisionSurface
    initialisation : dict
        :func:`choose_initial`'s summary.
    image : ndarray float32
        The preview the seeds come from; ``extent`` its grid (mm).
    extent : tuple
    finer : float or None
        The finer preview's voxel (mm) when one was made.
    """
    mark = clock.mark if clock is not None else (lambda name: None)
    image, extent = settings_preview(data, geometry, contrast, settings)
    mark("preview")
    surfaces, initialisation = settings_initial(image, extent, contrast, projector, data, settings)
    finer = _finer_voxel(settings, surfaces, geometry, data, contrast)
    if finer is not None:  # bubbles a few voxels across: seeded again in a preview fine enough for them
        mark("initial_bubbles")
        image, extent = settings_preview(data, geometry, contrast, replace(settings, voxel_size=finer))
        mark("preview")
        surfaces, initialisation = settings_initial(image, extent, contrast, projector, data, settings)
    return surfaces, initialisation, image, extent, finer


def settings_preview(data, geometry, contrast, settings):
    """The pipeline's voxel preview of ``data`` (bubbles positive): ``(image, extent)``."""
    return voxel_preview(data, geometry, contrast, settings.voxel_size, progress=settings.progress,
                         method=settings.preview, extend=preview_extension(settings.fov_model, data, contrast))


def settings_initial(image, extent, contrast, projector, data, settings):
    """The pipeline's initial bubbles in the preview (:func:`choose_initial` with ``settings``'s options):
    ``(surfaces, summary)``. ``auto`` compares the candidate sets after their radius-only fits, here."""
    detector = default_detector(settings.detector, projector.geometry.ndim)
    return choose_initial(image, extent, contrast, projector, data, detector=detector,
                          estimate=settings.estimate_radii and detector == "auto", progress=settings.progress,
                          control_points=settings.control_points, levels=settings.levels, radius=settings.radius,
                          min_distance=settings.min_distance, border_is_background=not settings.fov_model)


def coarse_radii(surfaces, geometry, data, factor, settings):
    """The radius-only pre-fit (:func:`estimate_radii`) on the detector binned by ``factor`` (the fit's
    coarsest level: the radii need not see every pixel), at that level's subdivision
    (:func:`coarse_surfaces`, as the fit's binned level); the surfaces come back at their own."""
    coarse = MeshProjector(geometry.binned(factor), supersampling=settings.supersampling)
    levels = [x.levels for x in surfaces]
    return coarse_surfaces(estimate_radii(coarse, coarse_surfaces(surfaces, factor, levels),
                                          ScanGeometry.bin_projections(data, factor), progress=settings.progress),
                           1, levels)


def _finer_voxel(settings, surfaces, geometry, data, contrast):
    """:func:`voxel_for_bubbles` of ``surfaces`` (their equivalent radii) against the default preview
    voxel; None when the voxel size is asked for (``settings.voxel_size``) or the bubbles are wide enough
    in voxels."""
    if settings.voxel_size is not None or not surfaces:
        return None
    return voxel_for_bubbles([x.fine().equivalent_radius for x in surfaces], geometry, preview_voxel_size(geometry),
                             preview_extension(settings.fov_model, data, contrast))


def _separation(settings, data, n_bubbles, voxel):
    """The fit's separation penalty (:mod:`bubsub.clients.optimise.separation`), or None when switched off."""
    if not settings.separation:
        return None
    from functools import partial

    from bubsub.clients.optimise.separation import separation_penalty, separation_weight

    return partial(separation_penalty, weight=separation_weight(data, n_bubbles, voxel, settings.separation),
                   gap=0.25 * voxel)


class _PhaseClock:
    """Wall and CPU seconds (this process, all threads) of consecutive phases, for ``report.json``."""

    def __init__(self):
        self._wall, self._cpu = time.perf_counter(), time.process_time()
        self._parts = {}

    def mark(self, name):
        """End the phase ``name`` now (added to its earlier time when it ran before); the next one starts
        (with the phase's freed memory given back: :func:`bubsub.core.malloc.release_free_memory`)."""
        release_free_memory()
        wall, cpu = time.perf_counter(), time.process_time()
        w0, c0 = self._parts.get(name, (0.0, 0.0))
        self._parts[name] = (w0 + wall - self._wall, c0 + cpu - self._cpu)
        self._wall, self._cpu = wall, cpu

    def parts(self):
        """``({phase: wall seconds}, {phase: CPU seconds})``."""
        return {k: w for k, (w, _) in self._parts.items()}, {k: c for k, (_, c) in self._parts.items()}


def prune(surfaces, min_radius, fov=None):
    """Drop bubbles the fit collapsed or turned inside out (spurious initial centres), and slivers at the
    field of view's edge.

    A bubble stays when its subdivided surface's equivalent radius (of the
    disc or ball of its area or volume) is at least ``min_radius`` and, with
    ``fov``, when the part of it inside ``fov`` is at least that disc or ball.
    The pipeline passes, after its last change, the slab between the planes
    of the detector's top and bottom rows (:func:`seen_slab`): no ray passes
    beyond them, so the rest of a cut bubble is continued from what the data
    see (:func:`.repair.continued`), not measured. On the ~600-bubble column
    of ``bubsub bench scale`` a 0.00037 mm^3 sliver at the detector's top row
    (a ball of one preview voxel: 0.0008 mm^3) sat on a cut bubble found
    whole: the one spurious bubble of the benchmark.

    Parameters
    ----------
    surfaces : list of SubdivisionSurface
    min_radius : float
        mm.
    fov : (r_xy, half_z), optional
        mm (as :func:`.fov.field_of_view`); None: whole bubbles only.

    Returns
    -------
    kept : list of SubdivisionSurface
    dropped : int
    """
    kept = []
    for s in surfaces:
        fine = s.fine()
        if fine.equivalent_radius >= min_radius and (fov is None or _seen_enough(fine, fov, min_radius)):
            kept.append(s)
    return kept, len(surfaces) - len(kept)


def seen_slab(geometry):
    """``(inf, half_z)``: the part of space between the planes of a 3D detector's top and bottom rows, which
    :func:`prune` asks a cut bubble to fill enough of; None in 2D (every bubble is seen whole)."""
    return (np.inf, field_of_view(geometry)[1]) if geometry.ndim == 3 else None


def _seen_enough(fine, fov, min_radius):
    """Whether a refined bubble inside the field of view ``fov`` (or its part there) is at least a disc or
    ball of ``min_radius``; bubbles wholly inside are not rasterised."""
    if inside_fov(fine.vertices, fov).all():
        return True
    # 24 cells across: within a per cent or so of the 48 the outputs use, at a quarter of the time
    return equivalent_radius(size_inside_fov(fine, fov, samples=24), fine.vertices.shape[1]) >= min_radius
