"""4D BubSub: a dynamic scan reconstructed subscan by subscan, backwards in time.

The last selected subscan is reconstructed as a static scan (voxel preview,
centres, radius estimation, BFGS: :func:`bubsub.clients.pipeline.reconstruct.reconstruct`).
Every earlier subscan starts from its successor's bubbles, each control mesh
shrunk toward its centroid and remeshed (:func:`bubsub.core.projection.remesh.warm_start`),
then BFGS; no voxel preview. Bubbles only shrink and vanish going backwards:
a bubble that collapses (or whose warm start cannot be built) ends its track,
the others keep their ids.

Two layers, so that another engine can run the same step on workers:

* :func:`reconstruct_subscan` -- one subscan: a pure, picklable function
  ``(scan, previous, settings, index, time) -> SubscanResult``; its inputs and
  output are plain data (arrays, tuples, dataclasses), never projectors.
* :func:`run_chain` -- the local driver: subscans in descending order, each
  from the previous result, with progress over subscans and Ctrl-C handling;
  :func:`reconstruct_dynamic` adds the output folder, ``--resume`` and the
  summary files (:mod:`bubsub.clients.pipeline.dynamic_outputs`).
"""

from __future__ import annotations

import dataclasses
import time as _time

import numpy as np

from bubsub.core import MeshProjector, SubdivisionSurface
from bubsub.core.metrics import projection_mse
from bubsub.core.projection.mesh import Mesh, Polygon
from bubsub.core.projection.remesh import SHRINK, warm_start

__all__ = ["DynamicSettings", "BubbleState", "SubscanResult", "reconstruct_subscan", "run_chain", "reconstruct_dynamic"]


@dataclasses.dataclass(frozen=True)
class DynamicSettings:
    """What ``bubsub reconstruct4d`` can be told (defaults follow the paper).

    Attributes
    ----------
    iterations : int
        BFGS iterations per subscan (80).
    control_points : int, optional
        Per bubble: 42 (3D) / 9 (2D) by default, for the cold start and as
        the remeshing target.
    levels : int
        Subdivision levels (2).
    holdout : {None, "odd", "even"}
        Projections of every subscan kept aside and scored (held-out MSE).
    shrink : float
        Warm-start shrink factor toward each bubble's centroid (0.8).
    estimate_radii : bool
        Radius-only pre-fit of the cold start.
    supersampling : int
    min_radius : float, optional
        A bubble whose equivalent radius falls below this (mm) has collapsed
        and ends its track; default the static pipeline's preview voxel size.
    voxel_baseline : bool
        Also run the paper's voxel baseline (30 BB iterations, non-negative)
        on each subscan and record its held-out MSE.
    warm_rtol, warm_window : float, int
        A warm-started fit stops early once ``warm_window`` iterations have
        lowered the objective by less than ``warm_rtol`` of its value (it
        starts near the optimum and would spend its remaining iterations on
        the noise); ``warm_rtol=0`` always runs ``iterations``.
    progress : bool
    """

    iterations: int = 80
    control_points: int | None = None
    levels: int = 2
    holdout: str | None = None
    shrink: float = SHRINK
    estimate_radii: bool = True
    supersampling: int = 1
    min_radius: float | None = None
    voxel_baseline: bool = False
    warm_rtol: float = 1e-3
    warm_window: int = 5
    progress: bool = True

    def __post_init__(self):
        if isinstance(self.iterations, bool) or not isinstance(self.iterations, int) or self.iterations < 0:
            raise ValueError(f"iterations must be a non-negative integer, got {self.iterations!r}")
        if self.holdout not in (None, "odd", "even"):
            raise ValueError(f"holdout must be None, 'odd' or 'even', got {self.holdout!r}")
        if not self.warm_rtol >= 0:
            raise ValueError(f"warm_rtol must be >= 0, got {self.warm_rtol!r}")
        if not 0 < self.shrink <= 1.5:
            raise ValueError(f"shrink must be in (0, 1.5], got {self.shrink!r}")


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
    levels : int
    """

    ids: tuple
    vertices: tuple
    faces: tuple
    attenuation: float
    levels: int

    @classmethod
    def from_surfaces(cls, ids, surfaces, attenuation=None, levels=2):
        surfaces = list(surfaces)
        if surfaces:
            attenuation = surfaces[0].attenuation if attenuation is None else attenuation
            levels = surfaces[0].levels
        return cls(tuple(int(i) for i in ids), tuple(np.array(s.vertices) for s in surfaces),
                   tuple(None if s.ndim == 2 else np.array(s.control_faces) for s in surfaces),
                   float(attenuation if attenuation is not None else np.nan), int(levels))

    def surfaces(self):
        """The bubbles as SubdivisionSurface, in ``ids`` order."""
        out = []
        for v, f in zip(self.vertices, self.faces):
            control = Polygon(v, self.attenuation) if f is None else Mesh(v, f, self.attenuation)
            out.append(SubdivisionSurface(control, self.levels))
        return out

    def __len__(self):
        return len(self.ids)

    def __repr__(self):
        return f"BubbleState(ids={list(self.ids)!r}, attenuation={self.attenuation!r}, levels={self.levels})"


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
        ``seconds_parts`` (cold: ``preview_and_centres``, ``fit``, ``other``
        = radius estimation, topology rounds, repair, held-out MSE; warm:
        ``remesh``, ``fit``, ``holdout``; ``voxel_baseline`` when run),
        ``holdout_mse`` (with a holdout), ``bubbles``, ``diverged``,
        ``interrupted`` and for the cold start the static pipeline's report
        fields.
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
    from bubsub.clients.pipeline.reconstruct import ReconstructionSettings

    return ReconstructionSettings(iterations=settings.iterations, control_points=settings.control_points,
                                  levels=settings.levels, estimate_radii=settings.estimate_radii,
                                  supersampling=settings.supersampling, holdout=settings.holdout,
                                  progress=settings.progress,
                                  # warm starts remesh to control_points at `levels`: keep the cold start's alike
                                  refine=False)


def _split(scan, holdout):
    from bubsub.clients.pipeline.reconstruct import split_holdout as split

    return split(scan.geometry, scan.bubble_data, holdout)


def _cold(scan, settings):
    from bubsub.clients.pipeline.reconstruct import reconstruct

    rec = reconstruct(scan, _static_settings(settings))
    r = rec.report
    report = {"start": "cold", "iterations": r["iterations"], "evaluations": r["evaluations"],
              "objective": r["final_objective"],
              "initial_objective": r["initial_objective"], "bubbles_dropped_at_start": r["bubbles_dropped"],
              "interrupted": r["interrupted"], "holdout_mse": r.get("holdout_mse"), "stop_reason": r.get("stop_reason"),
              # radius estimation, topology rounds, validity check and repair, held-out MSE: the rest
              "seconds_parts": {"preview_and_centres": r["seconds_initialisation"], "fit": r["seconds_fit"],
                                "other": r["seconds_total"] - r["seconds_initialisation"] - r["seconds_fit"]}}
    ids = range(len(rec.surfaces))
    return BubbleState.from_surfaces(ids, rec.surfaces, scan.bubble_contrast, settings.levels), report, \
        rec.preview, rec.preview_extent


def _equivalent_radius(surface):
    fine = surface.fine()
    if surface.ndim == 3:
        return float(np.cbrt(max(fine.volume, 0.0) * 3 / (4 * np.pi)))
    return float(np.sqrt(max(fine.area, 0.0) / np.pi))


def _warm(scan, previous, settings):
    from bubsub.clients.optimise.levels import bin_factors, fit_levels
    from bubsub.clients.pipeline.preview import preview_voxel_size

    g_fit, d_fit, _, _ = _split(scan, settings.holdout)
    min_radius = settings.min_radius or preview_voxel_size(g_fit)
    ended = {}
    ids, starts = [], []
    t0 = _time.perf_counter()
    for i, s in zip(previous.ids, previous.surfaces()):
        try:
            starts.append(warm_start(s.with_attenuation(scan.bubble_contrast), shrink=settings.shrink,
                                     control_points=settings.control_points))
            ids.append(i)
        except ValueError as exc:
            ended[i] = f"no warm start: {exc}"
    report = {"start": "warm", "iterations": 0, "objective": None, "initial_objective": None,
              "interrupted": False, "diverged": False, "seconds_parts": {"remesh": _time.perf_counter() - t0}}
    if not starts:
        return BubbleState.from_surfaces([], [], scan.bubble_contrast, settings.levels), report, ended
    projector = MeshProjector(g_fit, supersampling=settings.supersampling)
    initial = float(projector.objective(starts, d_fit)[0])
    try:
        # the static pipeline's coarse-to-fine data levels, each ended on the warm plateau test
        result, levels = fit_levels(projector, starts, d_fit, factors=bin_factors(g_fit), iterations=settings.iterations,
                                    rtol=settings.warm_rtol if settings.warm_rtol > 0 else None,
                                    rtol_window=settings.warm_window, progress=settings.progress)
        report["fit_levels"] = levels
        if not np.isfinite(result.objective):
            raise FloatingPointError(f"objective {result.objective}")
    except (RuntimeError, ValueError, FloatingPointError) as exc:
        # a diverged fit is kept and flagged; the chain goes on from the last good state
        report.update(diverged=True, error=str(exc))
        return previous, report, {}
    report["seconds_parts"]["fit"] = result.seconds
    report.update(iterations=result.iterations, evaluations=result.evaluations, objective=result.objective,
                  interrupted=result.interrupted,
                  stop_reason="objective plateau" if result.stop_reason == "converged" else result.stop_reason,
                  initial_objective=initial)
    kept_ids, kept = [], []
    for i, s in zip(ids, result.surfaces):
        r = _equivalent_radius(s)
        if not np.all(np.isfinite(s.vertices)) or not r >= min_radius:
            ended[i] = f"collapsed (equivalent radius {r:.3g} mm < {min_radius:.3g} mm)"
        else:
            kept_ids.append(i)
            kept.append(s)
    return BubbleState.from_surfaces(kept_ids, kept, scan.bubble_contrast, settings.levels), report, ended


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
    if previous is None:
        state, report, preview, extent = _cold(scan, settings)
        ended = {}
        report["diverged"] = False
    else:
        state, report, ended = _warm(scan, previous, settings)
    parts = report.setdefault("seconds_parts", {})
    _, _, g_val, d_val = _split(scan, settings.holdout)
    if g_val is not None and report.get("holdout_mse") is None:
        t1 = _time.perf_counter()
        pred = MeshProjector(g_val, supersampling=settings.supersampling).forward(state.surfaces()) \
            if len(state) else np.zeros(g_val.shape, np.float32)
        report["holdout_mse"] = projection_mse(pred, d_val)
        parts["holdout"] = _time.perf_counter() - t1
    if settings.voxel_baseline and g_val is not None:
        from bubsub.clients.pipeline.voxel4d import voxel_baseline

        baseline = voxel_baseline(scan, settings.holdout)
        report["voxel_holdout_mse"] = baseline["holdout_mse"]
        parts["voxel_baseline"] = baseline["seconds"]
    from bubsub.clients.pipeline.fov import fov_report

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
    bar = None
    if settings.progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(indices), desc="subscans", unit="subscan", position=0)
    try:
        for k in indices:
            res = step(get_scan(k), state, settings, k, float(times[k]) if times is not None else float(k))
            if res.report.get("interrupted"):
                return results, True
            results.append(res)
            state = res.state
            if on_result is not None:
                on_result(res)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(bubbles=len(state), ended=len(res.ended))
    except KeyboardInterrupt:
        return results, True
    finally:
        if bar is not None:
            bar.close()
    return results, False


def _run_record(scan, layout, settings):
    return {"scan": str(scan.path) if scan.path else None, "projections_per_subscan": layout.per_subscan,
            "subscans": [layout.selected.start, layout.selected.stop], "holdout": settings.holdout,
            "dimension": scan.ndim, "levels": settings.levels, "iterations": settings.iterations,
            "warm_rtol": settings.warm_rtol, "warm_window": settings.warm_window}


def reconstruct_dynamic(scan, out, settings=None, *, projections_per_subscan=None, subscans=None, resume=False,
                        overwrite=False, client=None, chunks=1):
    """``bubsub reconstruct4d``: the whole chain into an output folder.

    Parameters
    ----------
    scan : Scan
        The dynamic scan (all projections in acquisition order).
    out : path
        Output folder: ``subscan_NNNN/``, ``tracks.csv``, ``report.json``,
        ``growth.png``, ``mse.png`` (:mod:`bubsub.clients.pipeline.dynamic_outputs`).
    settings : DynamicSettings, optional
    projections_per_subscan : int, optional
        If the scan file lacks the attribute (see :func:`bubsub.core.io.subscans.subscan_layout`).
    subscans : str or range, optional
        ``"A:B"``: subscans A..B-1 (default all).
    resume : bool
        Keep the complete subscan folders of an earlier run with the same
        settings and continue the chain from the earliest of them.
    overwrite : bool
        Start afresh in a folder holding an earlier run (its subscan folders
        are replaced as the new ones complete).
    client : dask.distributed.Client, optional
        Run one task per subscan on this cluster
        (:func:`bubsub.clients.cluster.dynamic.run_chunks`); None: here.
    chunks : int
        Cut the chain into this many chunks run in parallel, each cold-started
        at its last subscan, ids linked where they overlap (see
        :mod:`bubsub.clients.cluster.dynamic`); 1: one chain, as the paper.

    Returns
    -------
    dict
        The run's ``report.json``.
    """
    import json
    from pathlib import Path

    from bubsub.core.io.atomic import atomic_write_text
    from bubsub.core.io.subscans import subscan, subscan_layout, subscan_times
    from bubsub.clients.pipeline import dynamic_outputs as outputs

    settings = settings or DynamicSettings()
    layout = subscan_layout(scan, projections_per_subscan, subscans)
    times, unit = subscan_times(scan, layout)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    record = _run_record(scan, layout, settings)
    order = list(reversed(layout.selected))
    done = [i for i in outputs.complete_subscans(out) if i in layout.selected]
    run_file = out / "run.json"
    if done and not resume:
        if not overwrite:
            raise ValueError(f"{out} already holds {len(done)} complete subscan folder(s); pass --resume to "
                             f"continue that run, --overwrite to start again, or choose another --out")
        done = []
    if resume and run_file.is_file():
        before = json.loads(run_file.read_text())
        changed = sorted(k for k in record if k != "scan" and before.get(k) != record[k])
        if changed:
            raise ValueError(f"--resume: {out} was made with different {changed} "
                             f"({ {k: before.get(k) for k in changed} } vs { {k: record[k] for k in changed} })")
    if set(done) != set(order[: len(done)]):
        raise ValueError(f"--resume: the complete subscans {done} in {out} are not the latest ones of "
                         f"{layout.selected.start}..{layout.selected.stop - 1}; start again in another --out")
    atomic_write_text(run_file, json.dumps(record, indent=2))
    prior = [outputs.read_subscan_result(out, i, scan.bubble_contrast) for i in done]
    start = min(prior, key=lambda r: r.index).state if prior else None

    def write(result):
        outputs.write_subscan(out, result, scan.ndim, scan.path)

    if client is None and chunks == 1:
        results, interrupted = run_chain(
            lambda k: subscan(scan, layout, k), order[len(done):], settings, start=start, times=times,
            step=reconstruct_subscan, on_result=write)
        engine = {}
    else:
        from bubsub.clients.cluster.dynamic import ScanFileSubscans, run_chunks
        from bubsub.clients.cluster.engine import workers_of

        source = (ScanFileSubscans(str(scan.path), scan.bubble_contrast, layout.per_subscan) if scan.path
                  and client is not None else lambda k: subscan(scan, layout, k))
        results, interrupted, links = run_chunks(client, source, order[len(done):], settings, chunks=chunks,
                                                 start=start, times=times, on_result=write)
        engine = {"engine": "dask" if client is not None else "local", "workers": max(1, workers_of(client)),
                  "chunks": chunks, "chunk_links": links}
    return outputs.write_summary(out, prior + results, layout=layout, time_unit=unit, settings=settings,
                                 interrupted=interrupted, **engine)
