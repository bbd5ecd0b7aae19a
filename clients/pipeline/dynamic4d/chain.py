"""4D BubSub: a dynamic scan reconstructed subscan by subscan, backwards in time.

The last selected subscan is reconstructed as a static scan (voxel preview,
centres, radius estimation, BFGS: :func:`bubsub.clients.pipeline.reconstruct.reconstruct`), and two of its
bubbles on one cap at the detector's top or bottom edge made one
(:func:`bubsub.clients.pipeline.dynamic4d.caps.merged_cold_caps`).
Each subscan is fitted in the frame of its foam's flow, measured by the tracks' steps or, before they have
any, the data's row sums (:mod:`bubsub.clients.pipeline.dynamic4d.motion`), so that its bubbles stand where
they are at its mid-time. Every earlier subscan starts from its successor's bubbles, each control mesh
shrunk toward its centroid and remeshed (:func:`bubsub.core.projection.remesh.warm_start`),
then BFGS. After the warm fit, a voxel preview of the data as the cold
start's and the static pipeline's topology rounds look for what the fitted
bubbles leave unexplained (:mod:`bubsub.clients.pipeline.dynamic4d.detect`): bubbles the successor lacks are
added with new track ids, a bubble that is two here (a coalescence forward in
time) is split, and slivers that left the field of view are removed. A bubble
that collapses, leaves the field of view or whose warm start cannot be built
ends its track; the others keep their ids. Each subscan's report holds its
lineage (``new``, ``coalescences``, ``ended``), which
:func:`bubsub.clients.pipeline.dynamic4d.outputs4d.write_lineage` writes as
``lineage.csv`` in forward time.

A large parallel-beam subscan goes through slabs of detector rows with the
rules of ``bubsub reconstruct`` (:mod:`bubsub.clients.pipeline.regions.slabs`: one
slab per about 8 million pixels read by default; cone-beam and 2D subscans,
and ``holdout``, whole), one slab after another in this process: the cold
start is reconstructed slab by slab and stitched, the warm starts are fitted
slab by slab (:func:`~bubsub.clients.pipeline.regions.slabs.fit_known`), each bubble
kept, with its track id, from the slab whose core holds its warm start's
centroid.

Two layers, so that another engine can run the same step on workers:

* :func:`reconstruct_subscan` -- one subscan: a pure, picklable function
  ``(scan, previous, settings, index, time) -> SubscanResult``; its inputs and
  output are plain data (arrays, tuples, dataclasses), never projectors.
* :func:`run_chain` -- the local driver: subscans in descending order, each
  from the previous result, with progress over subscans and Ctrl-C handling;
  :func:`bubsub.clients.pipeline.reconstruct4d.reconstruct_dynamic` adds the
  output folder, ``--resume``, the cluster engine and the summary files
  (:mod:`bubsub.clients.pipeline.dynamic4d.outputs4d`).

It is one module on purpose: the settings, the chain's state (track ids, the next new id) and the result are
the step's own inputs and output, and a reader follows a subscan's step from its settings to its result here;
the warm detection (:mod:`bubsub.clients.pipeline.dynamic4d.detect`) and the files live apart.
"""

from __future__ import annotations

import dataclasses
import time as _time

import numpy as np

from bubsub.core import MeshProjector, SubdivisionSurface
from bubsub.core.malloc import release_free_memory
from bubsub.core.projection.backends.raster import release_stores
from bubsub.core.metrics import projection_mse
from bubsub.core.projection.mesh import Mesh, Polygon
from bubsub.core.projection.remesh import SHRINK, warm_start
from bubsub.core.validate import check_int

from bubsub.clients.optimise.levels import bin_factors, fit_levels
from bubsub.clients.pipeline.inputs.fov import field_of_view, fov_report, reaches_edge_rows, seen_by
from bubsub.clients.pipeline.dynamic4d.motion import START_MARGIN, flow_during, flow_in_data, measure_steps, predict
from bubsub.clients.pipeline.regions.local import scene_objective
from bubsub.clients.pipeline.static.preview import preview_voxel_size
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, reconstruct, split_holdout
from bubsub.clients.pipeline.static.resolution import levels_by_size
from bubsub.clients.pipeline.regions.slabs import (OBJECTIVE_NOTE, fit_known, known_halo, plan_slabs, reconstruct_slabs,
                                                   slab_count, slab_totals)
from bubsub.clients.pipeline.evaluation.voxel_baseline import voxel_baseline
from bubsub.clients.pipeline.dynamic4d.caps import merged_cold_caps
from bubsub.clients.pipeline.dynamic4d.detect import detect_warm, warm_voxel
from bubsub.clients.pipeline.dynamic4d.tracks import size_of
from bubsub.clients.progress import phase

__all__ = ["DynamicSettings", "STATIC_FIELDS", "BubbleState", "SubscanResult", "reconstruct_subscan", "run_chain"]


#: The fields of :class:`ReconstructionSettings`, which :class:`DynamicSettings` holds and reads through.
STATIC_FIELDS = frozenset(f.name for f in dataclasses.fields(ReconstructionSettings))


@dataclasses.dataclass(frozen=True, init=False)
class DynamicSettings:
    """What ``bubsub reconstruct4d`` can be told: the static pipeline's settings and the 4D ones.

    ``DynamicSettings(iterations=15, holdout="odd", shrink=0.9)`` sets fields
    of either kind; a field of :class:`ReconstructionSettings` is read through
    (``settings.iterations`` is ``settings.static.iterations``), so every
    static setting reaches the cold start and the warm fits use the ones they
    share with it (``iterations``, ``control_points``, ``levels``,
    ``holdout``, ``supersampling``, ``progress``).

    Attributes
    ----------
    static : ReconstructionSettings
        Of the cold start (:func:`bubsub.clients.pipeline.reconstruct.reconstruct`,
        with ``refine`` off: warm starts remesh to ``control_points`` at
        ``levels``, so the cold start's meshes stay alike); ``iterations`` is
        also each warm fit's cap, ``holdout`` the projections of every subscan
        kept aside and scored (held-out MSE).
    shrink : float
        Warm-start shrink factor toward each bubble's centroid (0.8).
    min_radius : float, optional
        A bubble whose equivalent radius falls below this (mm) has collapsed
        and ends its track; default the static pipeline's preview voxel size.
    voxel_baseline : bool
        Also run the paper's voxel baseline (30 BB iterations, non-negative)
        on each subscan and record its held-out MSE.
    detect : bool
        After each warm fit, look for bubbles the successor lacks and for coalescences
        (:mod:`~bubsub.clients.pipeline.dynamic4d.detect`), and make one of a cold start's two bubbles on one cap
        (:func:`~bubsub.clients.pipeline.dynamic4d.caps.merged_cold_caps`); ``--no-detect``: only refit the
        successor's bubbles, and the cold start is the static pipeline's.
    warm_rtol, warm_window : float, int
        A warm-started fit stops early once ``warm_window`` iterations have
        lowered the objective by less than ``warm_rtol`` of its value (it
        starts near the optimum and would spend its remaining iterations on
        the noise); ``warm_rtol=0`` always runs ``iterations``. The default
        0.2 %: on ``bubsub bench dynamic``'s noisy flowing foams it finds the
        same bubbles with the same DDI as 0.1 %, its warm fits a third shorter
        (docs/dynamic.md).
    slabs : int, optional
        Slabs of detector rows per subscan (``--slabs``); None: as ``bubsub
        reconstruct`` chooses (:func:`~bubsub.clients.pipeline.regions.slabs.slab_count`).
    slab_halo : int, optional
        Halo rows of the slabs (``--slab-halo``); None: the cold start's
        :func:`~bubsub.clients.pipeline.regions.slabs.estimate_halo`, a warm start's
        :func:`~bubsub.clients.pipeline.regions.slabs.known_halo` of its successor's bubbles.
    follow_flow : bool
        Each subscan is fitted in the frame of its foam's flow, so that its bubbles stand where they are at its
        mid-time (``ScanGeometry.moved``): the tracks' median step spread over the projections
        (:func:`~bubsub.clients.pipeline.dynamic4d.motion.flow_during`), else, where the tracks measured none
        (the cold start and the warm subscan after it), the flow along the axis that the data's row sums show
        (:func:`~bubsub.clients.pipeline.dynamic4d.motion.flow_in_data`, parallel beam); False
        (``--no-follow-flow``): the foam taken to stand still during a subscan.
    """

    static: ReconstructionSettings
    shrink: float = SHRINK
    min_radius: float | None = None
    voxel_baseline: bool = False
    warm_rtol: float = 2e-3
    warm_window: int = 5
    slabs: int | None = None
    slab_halo: int | None = None
    detect: bool = True
    follow_flow: bool = True

    def __init__(self, static=None, *, shrink=SHRINK, min_radius=None, voxel_baseline=False, warm_rtol=2e-3,
                 warm_window=5, slabs=None, slab_halo=None, detect=True, follow_flow=True, **static_fields):
        # the one thing a generated __init__ cannot do: take the static settings' fields as keywords too
        unknown = sorted(set(static_fields) - STATIC_FIELDS)
        if unknown:
            raise TypeError(f"DynamicSettings got unknown settings {unknown}")
        static = ReconstructionSettings() if static is None else static
        if static_fields:  # validated by ReconstructionSettings itself
            static = dataclasses.replace(static, **static_fields)
        values = {"static": static, "shrink": shrink, "min_radius": min_radius, "voxel_baseline": voxel_baseline,
                  "warm_rtol": warm_rtol, "warm_window": warm_window, "slabs": slabs, "slab_halo": slab_halo,
                  "detect": bool(detect), "follow_flow": bool(follow_flow)}
        for f in dataclasses.fields(self):
            object.__setattr__(self, f.name, values[f.name])
        self.__post_init__()

    def __post_init__(self):
        if self.slabs is not None and check_int(self.slabs, "slabs", 1) > 1 and self.static.holdout is not None:
            raise ValueError("holdout needs every subscan reconstructed whole (--slabs 1)")
        if self.slab_halo is not None:
            check_int(self.slab_halo, "slab_halo", 0)
        if not self.warm_rtol >= 0:
            raise ValueError(f"warm_rtol must be >= 0, got {self.warm_rtol!r}")
        if not 0 < self.shrink <= 1.5:
            raise ValueError(f"shrink must be in (0, 1.5], got {self.shrink!r}")

    def __getattr__(self, name):
        # only reached for names that are not attributes of their own (unpickling looks up __setstate__ first)
        static = self.__dict__.get("static")
        if static is None or name not in STATIC_FIELDS:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        return getattr(static, name)


@dataclasses.dataclass(frozen=True)
class BubbleState:
    """Bubbles with track ids, as plain arrays (pickles cheaply; no projector state).

    Attributes
    ----------
    ids : tuple of int
    vertices : tuple of (n_k, d) float arrays
        Control vertices, mm.
    faces : tuple of (m_k, 3) int arrays, or of None in 2D
    attenuation : float
        1/mm (the bubble contrast).
    levels : tuple of int
        Subdivision levels of each bubble (in 3D they follow its size: :mod:`.resolution`).
    next_id : int
        The first track id not used yet in the chain (new bubbles take ids from it upward, so that an id that
        ended is never given again); -1: one above the largest of ``ids``.
    steps : tuple
        Each bubble's step from its successor (:func:`~bubsub.clients.pipeline.dynamic4d.motion.measure_steps`),
        which predicts the next warm start; empty where none was measured (a cold start; ``--resume`` measures
        them again from the kept subscans).
    """

    ids: tuple
    vertices: tuple
    faces: tuple
    attenuation: float
    levels: tuple
    next_id: int = -1
    steps: tuple = ()

    def __post_init__(self):
        if self.next_id < 0:
            object.__setattr__(self, "next_id", 1 + max(self.ids, default=-1))

    @classmethod
    def from_surfaces(cls, ids, surfaces, attenuation=None, next_id=-1, steps=()):
        surfaces = list(surfaces)
        if surfaces:
            attenuation = surfaces[0].attenuation if attenuation is None else attenuation
        ids = tuple(int(i) for i in ids)
        return cls(ids, tuple(np.array(s.vertices) for s in surfaces),
                   tuple(None if s.ndim == 2 else np.array(s.control_faces) for s in surfaces),
                   float(attenuation if attenuation is not None else np.nan), tuple(int(s.levels) for s in surfaces),
                   max(int(next_id), 1 + max(ids, default=-1)), tuple(steps))

    def surfaces(self):
        """The bubbles as SubdivisionSurface, in ``ids`` order."""
        out = []
        for v, f, n in zip(self.vertices, self.faces, self.levels):
            control = Polygon(v, self.attenuation) if f is None else Mesh(v, f, self.attenuation)
            out.append(SubdivisionSurface(control, n))
        return out

    def __len__(self):
        return len(self.ids)

    def __repr__(self):
        return (f"BubbleState(ids={list(self.ids)!r}, attenuation={self.attenuation!r}, levels={list(self.levels)!r}, "
                f"next_id={self.next_id!r})")


@dataclasses.dataclass(frozen=True)
class SubscanResult:
    """Outcome of :func:`reconstruct_subscan`.

    Attributes
    ----------
    index : int
        Subscan index in the scan.
    time : float
        Mid-time of the subscan (seconds, or the index when the scan has no times).
    state : BubbleState
        The fitted bubbles with their track ids (the last good state when
        the fit diverged).
    ended : tuple of int
        Track ids that end here (collapsed or failed), with the reason in
        ``report["ended"]``.
    report : dict
        ``start`` (cold/warm), ``iterations``, ``evaluations`` (projections
        with gradient the fit made), ``objective``,
        ``initial_objective``, ``seconds`` (wall clock of the whole step:
        everything below, not the writing of the subscan folder),
        ``cpu_seconds`` (CPU time of this process over the step),
        ``seconds_parts`` and ``cpu_seconds_parts`` (wall and CPU seconds of
        each phase; cold: the static pipeline's phases, ``preview``,
        ``initial_bubbles``, ``radius_estimation``, ``fit``, ``topology``,
        ``validity``, ..., ``caps``; warm: ``remesh``, ``fit``, ``detect``,
        ``holdout``; ``voxel_baseline`` when run),
        ``holdout_mse`` (with a holdout), ``bubbles``, ``diverged``,
        ``interrupted`` and for the cold start the static pipeline's report
        fields and ``caps_merged`` (with ``detect``).
    preview, preview_extent : ndarray, tuple, optional
        The voxel preview of a cold start (for ``overlay.png``).
    """

    index: int
    time: float
    state: BubbleState
    ended: tuple
    report: dict
    preview: np.ndarray | None = None
    preview_extent: tuple | None = None


def _static_settings(settings):
    """The cold start's settings: ``settings.static`` without the refinement (warm starts remesh to
    ``control_points`` at ``levels``, so the cold start's meshes stay alike)."""
    return dataclasses.replace(settings.static, refine=False)


def _split(scan, holdout):
    return split_holdout(scan.geometry, scan.bubble_data, holdout)


def _slab_count(scan, settings, halo=None):
    """Slabs and halo rows of a subscan, by the rules of ``bubsub reconstruct``; ``halo``: the default halo when
    ``settings.slab_halo`` is None (None: :func:`~bubsub.clients.pipeline.regions.slabs.estimate_halo`)."""
    halo = settings.slab_halo if settings.slab_halo is not None else halo
    return slab_count(scan, scan.geometry, _static_settings(settings), settings.slabs, halo,
                      whole_needed=settings.holdout is not None)


def _cold(scan, settings):
    slabs, halo = _slab_count(scan, settings)
    static = _static_settings(settings)
    # the dynamic scan's bubble signal is checked whole before any subscan (reconstruct4d.reconstruct_dynamic)
    rec = reconstruct(scan, static, signal_checked=True) if slabs == 1 else \
        reconstruct_slabs(scan, static, slabs=slabs, halo=halo, signal_checked=True)
    r = rec.report
    report = {"start": "cold", "iterations": r["iterations"], "evaluations": r["evaluations"],
              "objective": r["final_objective"],
              "initial_objective": r["initial_objective"], "bubbles_dropped_at_start": r["bubbles_dropped"],
              "interrupted": r["interrupted"], "holdout_mse": r.get("holdout_mse"), "stop_reason": r.get("stop_reason"),
              # the voxel the preview used: the default contact gap of bubsub analyse on the 4D folder
              "preview": r.get("preview"),
              # the static pipeline's phases (preview, initial_bubbles, radius_estimation, fit, topology,
              # validity, ...), wall and CPU seconds
              "seconds_parts": dict(r["seconds_parts"]), "cpu_seconds_parts": dict(r["cpu_seconds_parts"])}
    if slabs > 1:
        report.update({k: r[k] for k in ("slabs", "slab_halo_rows", "stitch", "objective_note")})
    surfaces = rec.surfaces
    if settings.detect and surfaces:
        t0 = _time.perf_counter(), _time.process_time()
        geometry, data = _split(scan, settings.holdout)[:2]
        touch = 2 * warm_voxel(geometry, data, scan.bubble_contrast, settings, surfaces)
        surfaces, merged, objective = merged_cold_caps(MeshProjector(geometry, supersampling=settings.supersampling),
                                                       data, surfaces, settings, touch=touch)
        report["caps_merged"] = len(merged)
        if objective is not None:
            report["objective"] = objective
        _mark(report, "caps", t0)
    return BubbleState.from_surfaces(range(len(surfaces)), surfaces, scan.bubble_contrast), report, \
        rec.preview, rec.preview_extent


def _warm_starts(scan, previous, successor, settings):
    """The successor's bubbles (``successor``: ``previous.surfaces()``) moved, shrunk and remeshed: their ids, the
    starts, and the ids that have none.

    Where the successor's tracks measured their last step, each bubble is moved by its neighbours' median
    displacement and scaled to :data:`~bubsub.clients.pipeline.dynamic4d.motion.START_MARGIN` of its predicted
    size (:func:`~bubsub.clients.pipeline.dynamic4d.motion.predict`; never below ``settings.shrink``, never
    above the successor's size); elsewhere it is shrunk by ``settings.shrink`` in place. A bubble cut by the
    detector's top or bottom row is remeshed unshrunk: its centroid lies toward the unseen part, so shrinking
    toward it would carry the visible cap out of view, where no gradient brings it back.
    """
    fov = field_of_view(scan.geometry) if scan.ndim == 3 else None
    margin = fov_report(scan.geometry)["margin"] if fov is not None else 0.0
    ids, starts, ended = [], [], {}
    shifts, ratios = predict(successor, previous.steps)
    for i, s, shift, ratio in zip(previous.ids, successor, shifts, ratios):
        cut = fov is not None and reaches_edge_rows(s.fine().vertices, fov[1], margin)
        shrink = settings.shrink if np.isnan(ratio) else max(settings.shrink, min(1.0, START_MARGIN * ratio))
        try:
            moved = s.with_vertices(np.asarray(s.vertices) + shift) if np.any(shift) else s
            starts.append(warm_start(moved.with_attenuation(scan.bubble_contrast), shrink=1.0 if cut else shrink,
                                     control_points=settings.control_points))
            ids.append(i)
        except ValueError as exc:
            ended[i] = f"no warm start: {exc}"
    return ids, starts, ended


def _warm_fit(geometry, data, starts, settings):
    """One warm fit: the fitted bubbles and its report (the static pipeline's coarse-to-fine data levels, each
    ended on the warm plateau test).

    Raises
    ------
    FloatingPointError
        When the objective is not finite.
    """
    projector = MeshProjector(geometry, supersampling=settings.supersampling)
    initial = scene_objective(projector, starts, data)  # a projection without the gradient: reported only
    result, levels = fit_levels(projector, starts, data, factors=bin_factors(geometry), iterations=settings.iterations,
                                rtol=settings.warm_rtol if settings.warm_rtol > 0 else None,
                                rtol_window=settings.warm_window, progress=settings.progress)
    if not np.isfinite(result.objective):
        raise FloatingPointError(f"objective {result.objective}")
    return list(result.surfaces), {
        "iterations": result.iterations, "evaluations": result.evaluations, "final_objective": result.objective,
        "initial_objective": initial, "interrupted": result.interrupted, "fit_levels": levels,
        "stop_reason": "objective plateau" if result.stop_reason == "converged" else result.stop_reason,
        "seconds_fit": result.seconds}


_WARM_SUMMED = ("iterations", "evaluations", "final_objective", "initial_objective", "seconds_fit")


def _warm_slabs(scan, successor, settings):
    """A warm subscan's slabs and halo: unless ``--slab-halo``, the halo of its successor's bubbles
    (``successor``), which the fits grow its shrunk starts back toward (a warm subscan has no preview to estimate it
    from)."""
    return _slab_count(scan, settings, halo=known_halo(successor, scan.geometry) if scan.ndim == 3 else None)


def _fit_slabs(scan, starts, settings, slabs, halo):
    """The warm starts fitted slab by slab (ownership: :func:`~bubsub.clients.pipeline.regions.slabs.fit_known`), and the
    fit's report fields: totals over the slabs, each slab's entry and the ownership summary."""
    plan = plan_slabs(scan.geometry.det_rows, slabs, halo)
    fitted, entries, summary = fit_known(scan, starts, lambda g, d, s: _warm_fit(g, d, s, settings), plan)
    return fitted, dict(slab_totals(entries, _WARM_SUMMED), slabs=entries, slab_halo_rows=halo, stitch=summary,
                        objective_note=OBJECTIVE_NOTE)


def _mark(report, name, since):
    """Add the wall and CPU seconds (this process, all threads) from ``since`` to phase ``name`` of
    ``report``'s ``seconds_parts`` and ``cpu_seconds_parts``; the clock readings now, for the next phase."""
    release_free_memory()  # the phase's freed arrays go back to the system: the peak RSS of the process
    now = _time.perf_counter(), _time.process_time()
    for key, t, t0 in (("seconds_parts", now[0], since[0]), ("cpu_seconds_parts", now[1], since[1])):
        parts = report.setdefault(key, {})
        parts[name] = parts.get(name, 0.0) + t - t0
    return now


def _warm(scan, previous, settings):
    t0 = _time.perf_counter(), _time.process_time()
    # built once for the starts, the slabs and the detection's sizes (each build subdivides every remeshed control
    # mesh, its own connectivity, again), and not held through the fit and the detection, where the run's peak
    # memory is
    successor = previous.surfaces()
    ids, starts, ended = _warm_starts(scan, previous, successor, settings)
    sizes = {int(i): size_of(s) for i, s in zip(previous.ids, successor)}
    report = {"start": "warm", "iterations": 0, "objective": None, "initial_objective": None,
              "interrupted": False, "diverged": False}
    t0 = _mark(report, "remesh", t0)
    if not starts:
        return BubbleState.from_surfaces([], [], scan.bubble_contrast, previous.next_id), report, ended
    # a bubble that grew or shrank since its successor's fit takes the levels of its size
    starts = levels_by_size(starts, scan.geometry, settings.levels, settings.facet_pixels)
    slabs, halo = _warm_slabs(scan, successor, settings)  # before the fit: a refused slab setting is no divergence
    del successor
    try:
        fitted, fields = _warm_fit(*_split(scan, settings.holdout)[:2], starts, settings) if slabs == 1 else \
            _fit_slabs(scan, starts, settings, slabs, halo)
    except (RuntimeError, ValueError, FloatingPointError) as exc:
        # a diverged fit is kept and flagged; the chain goes on from the last good state
        report.update(diverged=True, error=str(exc))
        return previous, report, {}
    fields.pop("seconds_fit")
    # the fit's crossing store (160 MB resident) is not kept through the detection's voxel preview, the warm
    # subscan's peak memory; the detection's fits allocate their own
    release_stores()
    t0 = _mark(report, "fit", t0)  # with the projectors' set-up and the initial objective
    report["objective"] = fields.pop("final_objective")
    report.update(fields)
    next_id = previous.next_id
    if settings.detect:
        ids, fitted, lineage, report["detection"], next_id = _detect(scan, previous, sizes, ids, fitted, settings)
        t0 = _mark(report, "detect", t0)
        ended.update(lineage.pop("removed"))
        for c in lineage["coalescences"]:
            ended[c["parent"]] = "coalescence (going backwards: split into {} and {})".format(*c["children"])
        if report["detection"].get("objective") is not None:
            report["objective"] = report["detection"]["objective"]
    else:
        lineage = {"new": {}, "coalescences": []}
    kept_ids, kept = _survivors(ids, fitted, scan, settings, ended)
    steps = measure_steps(previous.ids, previous.surfaces(), kept_ids, kept, scan.geometry)
    # a bubble found here that is too small to keep has no track: only the successor's tracks end
    known = set(previous.ids)
    ended = {i: why for i, why in ended.items() if i in known}
    alive = set(kept_ids)
    report["new"] = {str(i): v for i, v in sorted(lineage["new"].items()) if i in alive}
    report["coalescences"] = [c for c in lineage["coalescences"] if set(c["children"]) <= alive]
    return BubbleState.from_surfaces(kept_ids, kept, scan.bubble_contrast, next_id, steps), report, ended


def _detect(scan, previous, sizes, ids, fitted, settings):
    """:func:`~bubsub.clients.pipeline.dynamic4d.detect.detect_warm` on the fitted projections (the whole subscan, after
    its slabs too); ``sizes``: ``id -> size`` of the successor's bubbles."""
    geometry, data = _split(scan, settings.holdout)[:2]
    return detect_warm(geometry, data, ids, fitted, settings, successor_sizes=sizes, next_id=previous.next_id)


#: A warm-started bubble cut by the detector's top or bottom edge whose part in view is less deep than this
#: many detector rows ends its track (it left the field of view): the rows see too little of it to place its
#: surface, and a fit keeps such a sliver of a bubble that has left, where going backwards in time a flowing
#: foam carries bubbles out (``bubsub bench dynamic``: the slivers under two rows deep were bubbles already
#: gone, the caps kept from two rows on true ones).
MIN_EDGE_ROWS = 2


def edge_depth(surface, geometry):
    """How deep (mm) a 3D bubble cut by the detector's top or bottom edge plane reaches into the field of view;
    inf for one cut by neither or by both."""
    z = surface.fine().vertices[:, 2]
    half = field_of_view(geometry)[1]
    top, bottom = z.max() > half, z.min() < -half
    if top == bottom:
        return np.inf
    return float(half - max(z.min(), -half)) if top else float(min(z.max(), half) + half)


def _survivors(ids, fitted, scan, settings, ended):
    """The fitted bubbles that have not collapsed or left the field of view, and their ids; the others end,
    their reason put in ``ended``."""
    # the geometry of the fitted projections; scan.data, whose split is a view, rather than a copy of bubble_data
    geometry = split_holdout(scan.geometry, scan.data, settings.holdout)[0]
    min_radius = settings.min_radius or preview_voxel_size(geometry)
    row = 2 * field_of_view(geometry)[1] / geometry.det_rows if geometry.ndim == 3 else 0.0  # at the axis
    kept_ids, kept = [], []
    for i, s in zip(ids, fitted):
        r = s.fine().equivalent_radius
        if not np.all(np.isfinite(s.vertices)) or not r >= min_radius:
            ended[i] = f"collapsed (equivalent radius {r:.3g} mm < {min_radius:.3g} mm)"
        elif not np.any(seen_by(s.fine().vertices, geometry)):
            ended[i] = "left the field of view (no ray of the subscan sees it)"
        elif geometry.ndim == 3 and (depth := edge_depth(s, geometry)) < MIN_EDGE_ROWS * row:
            ended[i] = (f"left the field of view (a sliver {depth * 1e3:.0f} um deep in view, "
                        f"less than {MIN_EDGE_ROWS} detector rows)")
        else:
            kept_ids.append(i)
            kept.append(s)
    return kept_ids, kept


def _flow(scan, previous, settings):
    """The foam's displacement at each projection from the mid-time (:func:`~.motion.flow_during` of the
    successor's steps, else :func:`~.motion.flow_in_data`) and its source (``"tracks"``, ``"data"``), or
    ``(None, None)``: not followed."""
    if not settings.follow_flow:
        return None, None
    flow = flow_during(previous.steps, scan.n_angles, scan.time, scan.ndim) if previous is not None else None
    if flow is not None:
        return flow, "tracks"
    flow = flow_in_data(scan.bubble_data, scan.geometry, scan.bubble_contrast, scan.time)
    return (None, None) if flow is None else (flow, "data")


def reconstruct_subscan(scan, previous, settings, index=0, time=0.0):
    """Reconstruct one subscan: cold (``previous`` None) or warm-started from its successor.

    A pure function of its arguments, all picklable, so that any engine (a
    Dask worker, a SLURM array task) can run it.

    Parameters
    ----------
    scan : Scan
        The subscan as a static scan (:func:`bubsub.core.io.subscans.subscan`).
    previous : BubbleState or None
        The successor subscan's bubbles (track ids kept); None for a cold
        start (voxel preview, new ids 0..n-1).
    settings : DynamicSettings
    index : int
        The subscan's index (recorded in the result).
    time : float
        Its mid-time (recorded).

    Returns
    -------
    SubscanResult
    """
    t0, cpu0 = _time.perf_counter(), _time.process_time()
    preview = extent = None
    flow, source = _flow(scan, previous, settings)
    if flow is not None:  # the bubbles fitted where they stand at the mid-time
        scan = dataclasses.replace(scan, geometry=scan.geometry.moved(flow))
    if previous is None:
        state, report, preview, extent = _cold(scan, settings)
        ended = {}
        report["diverged"] = False
    else:
        state, report, ended = _warm(scan, previous, settings)
    # the foam's displacement over a subscan forward in time, as followed (None: not followed), and whence
    report["flow_mm"] = None if flow is None else ((flow[-1] - flow[0]) * len(flow) / (len(flow) - 1)).tolist()
    report["flow_from"] = source
    _, _, g_val, d_val = _split(scan, settings.holdout)
    if g_val is not None and report.get("holdout_mse") is None:
        t1 = _time.perf_counter(), _time.process_time()
        pred = MeshProjector(g_val, supersampling=settings.supersampling).forward(state.surfaces()) \
            if len(state) else np.zeros(g_val.shape, np.float32)
        report["holdout_mse"] = projection_mse(pred, d_val)
        _mark(report, "holdout", t1)
    if settings.voxel_baseline and g_val is not None:
        baseline = voxel_baseline(scan, settings.holdout)
        report["voxel_holdout_mse"] = baseline["holdout_mse"]
        report.setdefault("seconds_parts", {})["voxel_baseline"] = baseline["seconds"]
    # the field of view: bubbles.csv and tracks.csv flag the bubbles cut by its edge
    report.update(subscan=int(index), time=float(time), bubbles=len(state), field_of_view_mm=fov_report(scan.geometry),
                  ended={str(k): v for k, v in sorted(ended.items())}, seconds=_time.perf_counter() - t0,
                  cpu_seconds=_time.process_time() - cpu0)
    return SubscanResult(int(index), float(time), state, tuple(sorted(ended)), report, preview, extent)


def run_chain(get_scan, indices, settings, *, start=None, step=reconstruct_subscan, times=None,
              on_result=None):
    """Run :func:`reconstruct_subscan` over subscans in the given (descending) order, each from the last.

    Parameters
    ----------
    get_scan : callable(index) -> Scan
        The subscan's static scan.
    indices : sequence of int
        Subscans to reconstruct, latest first.
    settings : DynamicSettings
    start : BubbleState, optional
        The state after the subscan before ``indices[0]`` in the chain (a
        resumed run); None starts cold.
    step : callable
        The per-subscan function (:func:`reconstruct_subscan`).
    times : sequence of float, optional
        Mid-time per subscan index.
    on_result : callable(SubscanResult), optional
        Called as soon as a subscan is done (e.g. to write it).

    Returns
    -------
    results : list of SubscanResult
        The completed subscans; an interrupted fit stops the chain and is not
        included.
    interrupted : bool
    """
    results = []
    state = start
    # one line per finished subscan in a log (each=True): a run takes hours
    with phase("subscans", len(indices), unit="subscan", enabled=settings.progress, each=True) as bar:
        try:
            for k in indices:
                res = step(get_scan(k), state, settings, k, float(times[k]) if times is not None else float(k))
                if res.report.get("interrupted"):
                    bar.close("interrupted")
                    return results, True
                results.append(res)
                state = res.state
                if on_result is not None:
                    on_result(res)
                bar.update(1, subscan=k, bubbles=len(state), ended=len(res.ended))
        except KeyboardInterrupt:
            bar.close("interrupted")
            return results, True
    return results, False
