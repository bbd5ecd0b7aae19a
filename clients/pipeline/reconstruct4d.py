"""``bubsub reconstruct4d``: a dynamic scan's chain of subscans into an output folder.

:func:`reconstruct_dynamic` cuts the scan into subscans
(:mod:`bubsub.core.io.subscans`), runs the chain here
(:func:`bubsub.clients.pipeline.dynamic4d.chain.run_chain`) or in chunks on a Dask
cluster (:func:`bubsub.clients.cluster.chunks.run_chunks`), writes each
subscan's folder as soon as it is done, keeps the complete ones of an earlier
run for ``--resume`` (``run.json`` records the settings they were made with)
and ends with the summary files (:mod:`bubsub.clients.pipeline.dynamic4d.outputs4d`).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from bubsub.core.io.atomic import atomic_write_text
from bubsub.core.io.subscans import subscan, subscan_layout, subscan_times

from bubsub.clients.cluster.chunks import ScanFileSubscans, run_chunks
from bubsub.clients.cluster.engine import workers_of
from bubsub.clients.pipeline.dynamic4d import outputs4d as outputs
from bubsub.clients.pipeline.inputs.checks import check_bubble_signal
from bubsub.clients.pipeline.dynamic4d.chain import DynamicSettings, reconstruct_subscan, run_chain
from bubsub.clients.pipeline.dynamic4d.motion import measure_steps

__all__ = ["reconstruct_dynamic"]


def _run_record(scan, layout, settings):
    """What ``run.json`` records of a run: ``--resume`` refuses a folder made with other values."""
    return {"scan": str(scan.path) if scan.path else None, "projections_per_subscan": layout.per_subscan,
            "subscans": [layout.selected.start, layout.selected.stop], "holdout": settings.holdout,
            "dimension": scan.ndim, "levels": settings.levels, "iterations": settings.iterations,
            "warm_rtol": settings.warm_rtol, "warm_window": settings.warm_window, "slabs": settings.slabs,
            "slab_halo": settings.slab_halo, "detect": settings.detect, "follow_flow": settings.follow_flow}


def _kept_steps(prior, order, n_done, geometry):
    """The steps of the last kept subscan's tracks (:func:`~bubsub.clients.pipeline.dynamic4d.motion.measure_steps`),
    measured again from it and its successor, both on disk, so that a resumed run's next warm start is predicted as
    the uninterrupted run's is; none where it was the chain's first (cold) subscan."""
    if n_done < 2:
        return ()
    by_index = {r.index: r for r in prior}
    last, successor = by_index[order[n_done - 1]], by_index[order[n_done - 2]]
    if last.report.get("start") != "warm":
        return ()
    return measure_steps(successor.state.ids, successor.state.surfaces(), last.state.ids, last.state.surfaces(),
                         geometry)


def reconstruct_dynamic(scan, out, settings=None, *, projections_per_subscan=None, subscans=None, resume=False,
                        overwrite=False, client=None, chunks=1):
    """``bubsub reconstruct4d``: the whole chain into an output folder.

    Parameters
    ----------
    scan : Scan
        The dynamic scan (all projections in acquisition order).
    out : path
        Output folder: ``subscan_NNNN/``, ``tracks.csv``, ``report.json``,
        ``growth.png``, ``mse.png``, ``lineage.csv`` (:mod:`bubsub.clients.pipeline.dynamic4d.outputs4d`).
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
        (:func:`bubsub.clients.cluster.chunks.run_chunks`); None: here.
    chunks : int
        Cut the chain into this many chunks run in parallel, each cold-started
        at its last subscan, ids linked where they overlap (see
        :mod:`bubsub.clients.cluster.chunks`); 1: one chain, as the paper.

    Returns
    -------
    dict
        The run's ``report.json``.
    """
    settings = settings or DynamicSettings()
    layout = subscan_layout(scan, projections_per_subscan, subscans)
    times, unit = subscan_times(scan, layout)
    # the whole scan's signal and physics, before any file: a refused scan leaves no folder behind
    check_bubble_signal(scan, background_subtracted=settings.static.background_subtracted)
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
    if start is not None:  # new bubbles take ids above every id of the kept subscans, ended tracks' too
        used = {i for r in prior for i in (*r.state.ids, *r.ended)}
        start = dataclasses.replace(start, next_id=1 + max(used, default=-1),
                                    steps=_kept_steps(prior, order, len(done),
                                                      scan.geometry[layout.projections(order[0])]))

    def write(result):
        outputs.write_subscan(out, result, scan.ndim, scan.path)

    if client is None and chunks == 1:
        results, interrupted = run_chain(
            lambda k: subscan(scan, layout, k), order[len(done):], settings, start=start, times=times,
            step=reconstruct_subscan, on_result=write)
        engine = {}
    else:
        source = (ScanFileSubscans(str(scan.path), scan.bubble_contrast, layout.per_subscan) if scan.path
                  and client is not None else lambda k: subscan(scan, layout, k))
        results, interrupted, links = run_chunks(client, source, order[len(done):], settings,
                                                 step=reconstruct_subscan, chunks=chunks, start=start, times=times,
                                                 on_result=write)
        engine = {"engine": "dask" if client is not None else "local", "workers": max(1, workers_of(client)),
                  "chunks": chunks, "chunk_links": links}
    return outputs.write_summary(out, prior + results, layout=layout, time_unit=unit, settings=settings,
                                 interrupted=interrupted, **engine)
