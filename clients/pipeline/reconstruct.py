"""The BubSub reconstruction pipeline: scan file in, one mesh per bubble out.

:func:`reconstruct` runs its phases in order, each a function of this module
over a :class:`PhaseContext` (the local projector, the fitted data, the phase
clock, the report so far) with its options as keywords:

1. :func:`seed_phase`: low-resolution voxel reconstruction of the bubble data,
   the preview (:mod:`.preview`; box-constrained projected gradient by
   default), and the bubble centres in it: Laplacian-of-Gaussian blobs or
   distance-transform maxima of the Otsu mask, in 2D whichever explains the
   data better (:mod:`.initial`, :mod:`.seeding`), one spherical control mesh
   per bubble, or a user-given initial mesh.
2. :func:`radius_phase`: a radius-only fit (paper eq. 4-5), each bubble then
   subdivided as finely as its size needs (:mod:`.resolution`).
3. :func:`fit_phase`: BFGS on all control vertices, coarse to fine in the
   data: binned pixels first, the full detector last, each level ended on
   convergence (:mod:`bubsub.clients.optimise.levels`); for a foam wider than
   the detector, refitted with the detector's view-constant term eliminated
   and the contrast estimated again without it (:mod:`.detector_term`); then
   :func:`prune`.
4. :func:`topology_phase` (:mod:`.topology`; for a foam wider than the
   detector, the bubbles it added then refitted with their neighbours and the
   term eliminated, :func:`~.detector_term.added_bubbles_phase`),
   :func:`repair_phase` (the validity check and repair, :mod:`.repair`), each
   refitting only the bubbles it changed on detector windows (:mod:`.local`);
   :func:`refine_phase`: one coarse-to-fine step in the control meshes, kept
   when it explains the data better (:mod:`.refine`), and its check and
   repair; for a foam wider than the detector, every bubble refitted with the
   term eliminated and checked again (:func:`~.detector_term.final_refit_phase`);
   :func:`edge_phase`: slivers at the detector's edge;
   :func:`holdout_phase` with ``--holdout``. A tall parallel-beam scan is
   reconstructed slab by slab of detector rows (:mod:`.slabs`).
5. Outputs, each written atomically: ``bubbles.ply`` (3D) or ``bubbles.json``
   (2D), ``bubbles.csv`` (+ ``bubbles.csv-metadata.json``), ``report.json``,
   ``overlay.png``, ``sizes.png`` and (3D) ``meshes.png``
   (:func:`bubsub.clients.pipeline.results.outputs.write_outputs`, pictures by
   :mod:`bubsub.clients.pipeline.results.figures`).

One module on purpose: the phases read in the order the pipeline runs them.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np

from bubsub.core import MeshProjector
from bubsub.core.io.meshio import read_ply, read_polygons_json
from bubsub.core.metrics import projection_mse
from bubsub.core.projection.mesh import equivalent_radius
from bubsub.core.projection.subdivision import SubdivisionSurface

from bubsub.clients.optimise.levels import bin_factors, fit_levels
from bubsub.clients.optimise.separation import separation_penalty, separation_weight
from bubsub.clients.pipeline.inputs.checks import check_bubble_signal, check_setting_values, check_settings
from bubsub.clients.pipeline.inputs.fov import field_of_view, fov_report, inside_fov, size_inside_fov, unobserved_control
from bubsub.clients.pipeline.static.detector_term import added_bubbles_phase, detector_term_phase, final_refit_phase
from bubsub.clients.pipeline.static.initial import default_detector
from bubsub.clients.pipeline.regions.local import scene_objective
from bubsub.clients.pipeline.phase_report import PhaseClock, REMOTE_PHASES, merged_projector_report, projector_report
from bubsub.clients.pipeline.static.refine import can_refine, coarse_rate, control_counts, refine_and_check
from bubsub.clients.pipeline.static.repair import check_and_repair, merged_validity
from bubsub.clients.pipeline.static.resolution import level_counts, levels_by_size
from bubsub.clients.pipeline.static.seeding import (coarse_radii, coarse_radii_with, finer_voxel, initial_bubbles,
                                             settings_initial, settings_preview)
from bubsub.clients.pipeline.static.topology import adapt_bubbles

__all__ = ["ReconstructionSettings", "Reconstruction", "reconstruct", "PhaseContext", "PhaseClock", "Preview",
           "seed_phase", "radius_phase", "fit_phase", "topology_phase", "repair_phase", "refine_phase", "edge_phase",
           "holdout_phase", "load_initial", "split_holdout", "prune", "seen_slab", "settings_preview",
           "settings_initial", "coarse_radii", "initial_bubbles", "projector_report", "merged_projector_report",
           "REMOTE_PHASES"]


@dataclass(frozen=True)
class ReconstructionSettings:
    """What ``bubsub reconstruct`` can be told (defaults follow the paper); refused when made with a value no
    scan accepts (:func:`~bubsub.clients.pipeline.inputs.checks.check_setting_values`, ``ValueError`` naming the
    option), the rest when a scan's dimension is known (:func:`~bubsub.clients.pipeline.inputs.checks.check_settings`)."""

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

    def __post_init__(self):
        check_setting_values(self)


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


def reconstruct(scan, settings=None, *, init=None, projector_factory=None, signal_checked=False):
    """Reconstruct the bubbles of a scan: its phases, one after another.

    The scan's signal and the settings against its dimension are checked here, once per scan
    (:func:`~bubsub.clients.pipeline.inputs.checks.check_bubble_signal` unless ``signal_checked``,
    :func:`~bubsub.clients.pipeline.inputs.checks.check_settings`); the settings' values were checked when they
    were made.

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
        one that creates a remote job with the surfaces' topology
        (:func:`bubsub.clients.remote.jobs.remote_projectors`).
    signal_checked : bool
        ``scan`` is part of a scan whose bubble signal was checked whole (a subscan of
        :func:`~bubsub.clients.pipeline.reconstruct4d.reconstruct_dynamic`): not checked again.

    Returns
    -------
    Reconstruction
    """
    s = settings or ReconstructionSettings()
    check_settings(s, scan.ndim)
    if not signal_checked:
        check_bubble_signal(scan, background_subtracted=s.background_subtracted)
    clock = PhaseClock()
    contrast = scan.bubble_contrast
    g_fit, d_fit, g_val, d_val = split_holdout(scan.geometry, scan.bubble_data, s.holdout)
    run = PhaseContext(MeshProjector(g_fit, supersampling=s.supersampling), d_fit, clock)

    surfaces, preview = seed_phase(run, contrast, s, init=init)
    seeded_auto = default_detector(s.detector, g_fit.ndim) == "auto"  # its seeds come with their radii fitted
    surfaces = radius_phase(run, surfaces, estimate=s.estimate_radii and init is None and not seeded_auto,
                            data_levels=s.data_levels, levels=s.levels, facet_pixels=s.facet_pixels,
                            progress=s.progress)
    voxel = preview.voxel
    penalty = _separation(s.separation, d_fit, len(surfaces), voxel) if projector_factory is None else None
    refit = partial(fit_phase, factory=projector_factory, data_levels=s.data_levels, iterations=s.iterations,
                    rtol=s.fit_rtol, penalty=penalty, progress=s.progress)
    fit, term, contrast = detector_term_phase(run, surfaces, refit, contrast,
                                              enabled=s.fov_model and projector_factory is None)
    kept, dropped = prune(fit.surfaces, min_radius=voxel)
    interrupted = fit.interrupted  # Ctrl-C: no further changes, write what we have
    try:
        kept = topology_phase(run, kept, contrast, preview, rounds=s.topology_rounds if s.topology else 0,
                              enabled=not interrupted, iterations=s.iterations, levels=s.levels,
                              facet_pixels=s.facet_pixels, voxel_size=s.voxel_size, method=s.preview,
                              fov_model=s.fov_model, penalty=penalty, progress=s.progress)
        step = 0.0
        if run.report["topology"]:  # local tomography: what the rounds added, refitted with the term eliminated
            kept, step = added_bubbles_phase(run, kept, run.report["topology"]["changes"], iterations=s.iterations,
                                             penalty=penalty, progress=s.progress)
            term = term + step
        repair = partial(check_and_repair, projector=run.projector, data=run.data, repair=s.repair and not interrupted,
                         iterations=s.repair_iterations, gap=0.25 * voxel, penalty=penalty)
        will_refine = s.refine and init is None and not interrupted
        # the coarse bubbles' data term before the repair: the refinement's trial discounts the repair's rise in it
        # the rounds' final objective is the scene's when they ran and the added bubbles' refit changed nothing
        topology = run.report["topology"] if np.isscalar(step) else None
        reached = (topology["objective"] if topology else scene_objective(run.projector, kept, run.data)) \
            if will_refine and kept else None
        kept = repair_phase(run, kept, repair)
        kept = refine_phase(run, kept, repair, enabled=will_refine, iterations=s.refine_iterations, penalty=penalty,
                            progress=s.progress, rtol=s.fit_rtol, coarse_rate=coarse_rate(fit.history),
                            reached=reached)
        if not interrupted:  # local tomography: all bubbles refitted with the term eliminated, checked again
            kept, step = final_refit_phase(run, kept, repair, iterations=s.iterations, penalty=penalty,
                                           progress=s.progress)
            term = term + step
        kept = edge_phase(run, kept, min_radius=voxel)
    except KeyboardInterrupt:  # in the topology rounds, the repair or the refinement: report the bubbles as they were
        interrupted = True
        kept = repair_phase(run, kept, partial(check_and_repair, projector=run.projector, data=run.data, repair=False))

    report = _report(run, kept, fit, preview, s, scan.geometry, dropped=dropped, interrupted=interrupted)
    report.update({k: run.report[k] for k in ("detector_term",) if k in run.report})  # local tomography only
    if g_val is not None:
        report.update(holdout_phase(run, kept, g_val, d_val - term, supersampling=s.supersampling))
    # wall and CPU seconds of each phase (CPU: this process, all threads)
    report["seconds_parts"], report["cpu_seconds_parts"] = clock.parts()
    report["projector"] = projector_report(fit.remote, report["seconds_parts"], run.projector.backend)
    return Reconstruction(kept, report, preview.image, preview.extent)


@dataclass
class PhaseContext:
    """What the phases of :func:`reconstruct` share.

    Attributes
    ----------
    projector : MeshProjector
        Local, of the fitted projections (the projections not held out).
    data : ndarray, ``projector.geometry.shape``
        The fitted projections (bubbles' signal, ``scan.bubble_data``).
    clock : PhaseClock
        Each phase marks its end on it (``report.json``'s ``seconds_parts``).
    report : dict
        The phases' entries of ``report.json`` so far (``fit``, ``topology``, ``validity``, ...).
    """

    projector: MeshProjector
    data: np.ndarray
    clock: PhaseClock
    report: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Preview:
    """The voxel preview the bubbles were seeded in: ``image`` (float32, ``(slices, rows, cols)`` or
    ``(rows, cols)``), its ``extent`` (mm) and ``finer`` (the finer preview's voxel, mm, when the bubbles
    were a few voxels across; None otherwise)."""

    image: np.ndarray
    extent: tuple
    finer: float | None = None

    @property
    def voxel(self):
        """Voxel size, mm."""
        return (self.extent[1] - self.extent[0]) / self.image.shape[-1]


@dataclass(frozen=True)
class _Fit:
    """What :func:`fit_phase` hands on: the fitted ``surfaces``, ``history`` (the objective per iteration),
    ``interrupted``, and ``remote`` (the projector ``projector_factory`` made, or None)."""

    surfaces: list
    history: list
    interrupted: bool
    remote: object = None


def seed_phase(run, contrast, settings, *, init=None):
    """Phases ``preview`` and ``initial_bubbles``: the voxel preview and the bubbles seeded in it
    (:func:`initial_bubbles`), or ``init`` given contrast ``contrast`` with their preview. Its options are
    ``settings``' preview and seed options, read by :mod:`.seeding` as the benchmarks that start where the
    pipeline starts read them. Records ``initialisation``, ``bubbles_initial``, ``seconds_initialisation``.

    Returns
    -------
    surfaces : list of SubdivisionSurface
    preview : Preview
    """
    g, d = run.projector.geometry, run.data
    initialisation = None
    if init is None:
        surfaces, initialisation, image, extent, finer = initial_bubbles(d, g, contrast, run.projector, settings,
                                                                         clock=run.clock)
    else:
        surfaces = [x.with_attenuation(contrast) for x in init]
        finer = finer_voxel(settings, surfaces, g, d, contrast)
        image, extent = settings_preview(d, g, contrast, replace(settings, voxel_size=finer or settings.voxel_size))
        run.clock.mark("preview")
    run.report.update(initialisation=initialisation, bubbles_initial=len(surfaces),
                      seconds_initialisation=run.clock.elapsed())
    run.clock.mark("initial_bubbles")
    return surfaces, Preview(image, extent, finer)


def radius_phase(run, surfaces, *, estimate, data_levels, levels, facet_pixels, progress=False):
    """Phase ``radius_estimation``: the radius-only pre-fit on the fit's coarsest data level when
    ``estimate`` (:func:`coarse_radii`), then each bubble subdivided as finely as its size needs, at most
    ``levels`` (3D; :func:`~bubsub.clients.pipeline.static.resolution.levels_by_size`)."""
    g = run.projector.geometry
    if estimate:
        surfaces = coarse_radii_with(surfaces, g, run.data, bin_factors(g, data_levels)[0],
                                     supersampling=run.projector.supersampling, progress=progress)
    surfaces = levels_by_size(surfaces, g, levels, facet_pixels)
    run.clock.mark("radius_estimation")
    return surfaces


def fit_phase(run, surfaces, *, factory=None, data_levels=None, iterations=80, rtol=None, penalty=None,
              progress=False):
    """Phase ``fit``: BFGS on all control vertices, coarse to fine in the data
    (:func:`~bubsub.clients.optimise.levels.fit_levels`).

    The projections run on ``factory(geometry, data, surfaces)``'s projector (a remote job) when given,
    else on ``run.projector``. Records ``initial_objective`` (the starting bubbles' on the full detector),
    ``fit``, ``fit_levels`` and ``method``.

    Returns
    -------
    _Fit
    """
    g, d = run.projector.geometry, run.data
    if factory is None:
        projector, remote = run.projector, None
        f_start = projector.objective(surfaces, d)
    else:  # a remote job holds its surfaces' topology and levels: made once they are known
        projector = remote = factory(g, d, surfaces)
        f_start = projector.objective(surfaces)
    result, levels_report = fit_levels(projector, surfaces, d, factors=bin_factors(g, data_levels),
                                       iterations=iterations, rtol=rtol, penalty=penalty, progress=progress,
                                       factory=factory)
    run.clock.mark("fit")
    run.report.update(initial_objective=float(f_start[0]), method=result.method, fit_levels=levels_report,
                      fit={"objective": result.objective, "iterations": result.iterations,
                           "evaluations": result.evaluations, "stop_reason": result.stop_reason,
                           "seconds": result.seconds, "penalty": result.penalty})
    return _Fit(result.surfaces, result.history, result.interrupted, remote)


def topology_phase(run, surfaces, contrast, preview, *, rounds, enabled=True, **options):
    """Phase ``topology``: ``rounds`` rounds of adding, removing, merging and splitting bubbles
    (:func:`~bubsub.clients.pipeline.static.topology.adapt_bubbles` with ``options``, on ``preview``'s grid); none when
    ``rounds`` is 0, not ``enabled`` or there are no bubbles. Records ``topology`` (None when none ran)."""
    summary = None
    if enabled and rounds > 0 and surfaces:
        surfaces, summary = adapt_bubbles(run.projector, surfaces, run.data, contrast=contrast, voxel=preview.voxel,
                                          rounds=rounds, image=preview.image, extent=preview.extent, **options)
    run.report["topology"] = summary
    run.clock.mark("topology")
    return surfaces


def repair_phase(run, surfaces, repair):
    """Phase ``validity``: ``repair(surfaces)`` (:func:`~bubsub.clients.pipeline.static.repair.check_and_repair` with
    the pipeline's options) checks the bubbles and repairs them. Records ``validity``."""
    surfaces, run.report["validity"] = repair(surfaces)
    run.clock.mark("validity")
    return surfaces


def refine_phase(run, surfaces, repair, *, enabled=True, **options):
    """Phase ``refine``: one coarse-to-fine step in the control meshes, refitted, checked and repaired again
    by ``repair``, kept when the Akaike score improves
    (:func:`~bubsub.clients.pipeline.static.refine.refine_and_check` with ``options``); none unless ``enabled``
    and the bubbles can be refined. Records ``refinement`` and merges the second check into ``validity``."""
    refinement = None
    if enabled and can_refine(surfaces):
        # after the repair, so the refined fit also fills the gas of dropped bubbles; checked again
        surfaces, refinement, again = refine_and_check(run.projector, surfaces, run.data, repair, **options)
        if again is not None:
            run.report["validity"] = merged_validity(run.report["validity"], again)
    run.report["refinement"] = refinement
    run.clock.mark("refine")
    return surfaces


def edge_phase(run, surfaces, *, min_radius):
    """Phase ``edge_slivers`` (3D): slivers at the detector's top and bottom rows dropped once every change
    is made (:func:`prune` with :func:`seen_slab`). Records their number, ``edge_slivers_dropped``."""
    edge = seen_slab(run.projector.geometry)
    if edge is None:
        return surfaces
    surfaces, run.report["edge_slivers_dropped"] = prune(surfaces, min_radius=min_radius, fov=edge)
    run.clock.mark("edge_slivers")
    return surfaces


def holdout_phase(run, surfaces, geometry, data, *, supersampling=1):
    """Phase ``holdout``: the delivered bubbles' mean squared error on the held-out projections ``data`` of
    ``geometry``; their ``report.json`` entries."""
    pred = MeshProjector(geometry, supersampling=supersampling).forward(surfaces)
    entries = {"holdout_projections": geometry.n_angles, "holdout_mse": projection_mse(pred, data)}
    run.clock.mark("holdout")
    return entries


def _report(run, kept, fit, preview, s, geometry, *, dropped, interrupted):
    """``report.json`` of :func:`reconstruct`: the phases' entries and what was delivered."""
    r = run.report
    g_fit = run.projector.geometry
    refinement, validity = r.get("refinement"), r["validity"]
    refined = bool(refinement and refinement["kept"])
    # what was delivered: the bubbles written, after the topology rounds, the repair and a kept refined fit
    try:
        f_final = scene_objective(run.projector, kept, run.data)
    except KeyboardInterrupt:  # a second Ctrl-C: the outputs matter more than this figure
        f_final, interrupted = None, True
    fit_r = r["fit"]
    return {
        "bubbles": len(kept),
        "bubbles_initial": r["bubbles_initial"],
        "initialisation": r["initialisation"],
        # the voxel preview's grid; made finer for bubbles a few voxels across (.preview.voxel_for_bubbles)
        "preview": {"voxel_mm": preview.voxel, "shape": list(preview.image.shape),
                    "finer_for_bubbles": preview.finer is not None},
        "bubbles_dropped": dropped + r.get("edge_slivers_dropped", 0) + validity["dropped"],
        "validity": validity,
        "topology": r.get("topology"),
        "refinement": refinement,
        "dimension": geometry.ndim,
        # the fits that made the delivered bubbles: the fit, then the refined fit when it was kept
        "iterations": fit_r["iterations"] + (refinement["iterations"] if refined else 0),
        "evaluations": fit_r["evaluations"] + (refinement["evaluations"] if refined else 0),
        "delivered_fit": "refined fit" if refined else "fit",
        "fit": fit_r,
        "fit_levels": r["fit_levels"],
        # 0.5 ||Proj(S x) - d||^2 of the delivered bubbles on the fitted projections, as initial_objective
        "final_objective": f_final,
        "initial_objective": r["initial_objective"],
        "method": r["method"],
        "interrupted": interrupted,
        "stop_reason": "interrupted" if interrupted else (refinement["stop_reason"] if refined
                                                          else fit_r["stop_reason"]),
        "seconds_total": run.clock.elapsed(),
        "seconds_fit": fit_r["seconds"],
        "seconds_initialisation": r["seconds_initialisation"],
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


def _separation(strength, data, n_bubbles, voxel):
    """The fit's separation penalty of ``strength`` (:mod:`bubsub.clients.optimise.separation`), or None when
    it is 0 (off)."""
    if not strength:
        return None
    return partial(separation_penalty, weight=separation_weight(data, n_bubbles, voxel, strength), gap=0.25 * voxel)


def prune(surfaces, min_radius, fov=None):
    """Drop bubbles the fit collapsed or turned inside out (spurious initial centres), and slivers at the
    field of view's edge.

    A bubble stays when its subdivided surface's equivalent radius (of the
    disc or ball of its area or volume) is at least ``min_radius`` and, with
    ``fov``, when the part of it inside ``fov`` is at least that disc or ball.
    The pipeline passes, after its last change, the slab between the planes
    of the detector's top and bottom rows (:func:`seen_slab`): no ray passes
    beyond them, so the rest of a cut bubble is continued from what the data
    see (:func:`.repair.continued`), not measured: a sliver there is no
    evidence of a bubble (docs/prepare.md, "Slivers at the edge are dropped",
    measures it on ``bubsub bench scale``'s column).

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
