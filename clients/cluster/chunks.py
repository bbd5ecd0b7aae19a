"""4D runs on a cluster: one task per subscan, chained backwards in time, optionally in K chunks.

The subscan chain is sequential by nature (each subscan starts from its
successor's bubbles), so the tasks of one chain depend on each other:
``task(k)`` takes ``task(k + 1)``'s result. ``chunks=K`` cuts the chain into K
chunks that run in parallel; each chunk is cold-started at its last subscan,
which is also the first subscan of the next chunk in time. That shared
subscan is reconstructed twice (warm by the later chunk, whose result is kept,
and cold by the earlier one), and the earlier chunk's bubble ids are linked to
the later chunk's by a one-to-one matching of the two reconstructions by
overlap (:func:`link_ids`). Unmatched bubbles, and the bubbles an earlier
chunk's warm subscans find anew, take fresh ids (not used by any other track);
the unmatched ones are reported.

Results are written as they complete, once their ids are final: the latest
chunk's at once, an earlier chunk's as soon as its boundary is linked. So the
folders on disk are always the latest subscans of the range and ``--resume``
continues from them, as for an in-process run.

Workers read their subscan from the scan file (a shared filesystem; each
worker process reads the file once) rather than receiving projections
through the scheduler; a scan that has no file is shipped with its tasks.
"""

from __future__ import annotations

import dataclasses
import uuid
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.optimize import linear_sum_assignment

from bubsub.core.validate import check_int
from bubsub.clients.cluster.engine import distributed
from bubsub.clients.progress import phase
from bubsub.core.io.scanfile import read_scan
from bubsub.core.io.subscans import subscan, subscan_layout
from bubsub.core.projection.masks import label_image

__all__ = ["chunk_bounds", "link_ids", "relabel", "run_subscan", "run_chunks", "ScanFileSubscans"]

#: matched bubbles of the two reconstructions of a shared subscan overlap at least this much (IoU)
MIN_OVERLAP = 0.5


@dataclass(frozen=True)
class ScanFileSubscans:
    """Where a worker reads subscans: the scan file's path, contrast and subscan size."""

    path: str
    bubble_contrast: float
    projections_per_subscan: int

    def get(self, index):
        """Subscan ``index`` as a static Scan."""
        scan = _read_scan(self.path, self.bubble_contrast)
        return subscan(scan, subscan_layout(scan, self.projections_per_subscan), index)


@lru_cache(maxsize=1)
def _read_scan(path, bubble_contrast):
    return read_scan(path, bubble_contrast=bubble_contrast)


def run_subscan(step, source, index, previous, settings, time):
    """One subscan as a task: ``step`` on the subscan read from ``source``.

    Parameters
    ----------
    step : callable(scan, state, settings, index, time) -> SubscanResult
        Module-level (picklable): :func:`bubsub.clients.pipeline.dynamic4d.chain.reconstruct_subscan`.
    source : ScanFileSubscans or Scan
        The scan file to read from, or the subscan itself.
    index : int
    previous : SubscanResult, BubbleState or None
        The successor's result (a Dask future's value) or its state; None: cold start.
    settings : DynamicSettings
    time : float
    """
    scan = source.get(index) if isinstance(source, ScanFileSubscans) else source
    state = getattr(previous, "state", previous)  # a SubscanResult's state, or the state itself
    return step(scan, state, settings, index, time)


def chunk_bounds(order, chunks):
    """Cut ``order`` (subscans, latest first) into at most ``chunks`` chunks overlapping by one subscan.

    Returns
    -------
    list of list of int
        Each chunk latest first; chunk ``c``'s last subscan is chunk ``c + 1``'s first.
    """
    order = list(order)
    check_int(chunks, "chunks", 1)
    k = max(1, min(chunks, len(order) - 1))
    if k == 1:
        return [order]
    cuts = [round(c * (len(order) - 1) / k) for c in range(k + 1)]
    return [order[cuts[c]: cuts[c + 1] + 1] for c in range(k)]


def _grid(items, ndim, cells):
    """A grid around all ``items`` with about ``cells`` pixels (voxels) along its longest side."""
    pts = np.concatenate([np.asarray(s.fine().vertices) for s in items])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = 0.05 * float(np.max(hi - lo)) + 1e-9
    lo, hi = lo - pad, hi + pad
    step = float(np.max(hi - lo)) / cells
    n = np.maximum(4, np.ceil((hi - lo) / step).astype(int))
    hi = lo + n * step
    if ndim == 2:
        return (int(n[1]), int(n[0])), (lo[0], hi[0], lo[1], hi[1])
    return (int(n[2]), int(n[1]), int(n[0])), (lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])


def link_ids(earlier, later, min_overlap=MIN_OVERLAP):
    """Match two reconstructions of one subscan one-to-one by overlap.

    Parameters
    ----------
    earlier, later : BubbleState
        The earlier chunk's (cold) and the later chunk's (warm, final ids)
        bubbles of the shared subscan.
    min_overlap : float
        Least intersection over union of a matched pair.

    Returns
    -------
    matches : dict
        ``earlier id -> later id`` for the matched pairs.
    overlaps : dict
        ``earlier id -> IoU`` of each match.
    """

    a, b = earlier.surfaces(), later.surfaces()
    if not a or not b:
        return {}, {}
    ndim = a[0].ndim
    shape, extent = _grid(a + b, ndim, 256 if ndim == 2 else 96)
    la = label_image(a, shape, extent).ravel()
    lb = label_image(b, shape, extent).ravel()
    counts = np.bincount(la * (len(b) + 1) + lb, minlength=(len(a) + 1) * (len(b) + 1)).reshape(len(a) + 1, -1)
    inter = counts[1:, 1:].astype(float)
    union = counts[1:, :].sum(axis=1)[:, None] + counts[:, 1:].sum(axis=0)[None, :] - inter
    iou = np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)
    rows, cols = linear_sum_assignment(-iou)
    keep = iou[rows, cols] >= min_overlap
    matches = {earlier.ids[r]: later.ids[c] for r, c in zip(rows[keep], cols[keep])}
    overlaps = {earlier.ids[r]: float(iou[r, c]) for r, c in zip(rows[keep], cols[keep])}
    return matches, overlaps


def relabel(result, mapping):
    """``result`` (a SubscanResult) with its track ids replaced through ``mapping`` (in its state, its ended
    tracks and its lineage: ``new`` and ``coalescences``)."""
    state = dataclasses.replace(result.state, ids=tuple(mapping[i] for i in result.state.ids),
                                next_id=1 + max(mapping.values(), default=-1))
    ended = tuple(sorted(mapping[i] for i in result.ended))
    r = result.report
    report = dict(r, ended={str(mapping[int(k)]): v for k, v in r.get("ended", {}).items()})
    if "new" in r:
        report["new"] = {str(mapping[int(k)]): v for k, v in r["new"].items()}
    if "coalescences" in r:
        report["coalescences"] = [{"parent": mapping[int(c["parent"])],
                                   "children": [mapping[int(i)] for i in c["children"]]} for c in r["coalescences"]]
    return dataclasses.replace(result, state=state, ended=ended, report=report)


def drop_unwritten_ends(result, unwritten):
    """``result`` without the ends of tracks no written subscan holds.

    A chunk's cold start at the shared subscan can hold a bubble the later
    chunk's result there lacks (it gets a fresh id, as it may be a bubble the
    later chunk missed); the shared subscan is written from the later chunk.
    Where the next subscan drops that bubble too, its track never appears in
    the outputs, so its end (a birth, forwards in time) is no event to record.
    """
    gone = set(result.ended) & set(unwritten)
    if not gone:
        return result
    report = dict(result.report, ended={k: v for k, v in result.report.get("ended", {}).items()
                                        if int(k) not in gone})
    return dataclasses.replace(result, ended=tuple(i for i in result.ended if i not in gone), report=report)


class _Fresh(dict):
    """A chunk's id mapping that gives an id it does not hold the next fresh id (a bubble the chunk's warm
    subscans found anew), through ``take``."""

    def __init__(self, mapping, take):
        super().__init__(mapping)
        self.take = take

    def __missing__(self, key):
        self[key] = self.take()
        return self[key]


class _Linker:
    """Decides final ids chunk by chunk (latest first) and releases results once their ids are final.

    Chunk 0 keeps its ids. Chunk ``c``'s ids are known once chunk ``c - 1``
    is linked and has reached the shared subscan; its bubbles matched there
    take the later ids, the others fresh ids above every id used so far (in
    chunk order, so the numbering does not depend on which task ends first).
    """

    def __init__(self, chunks, start_ids=()):
        self.chunks = chunks
        self.mapping = {0: None}
        self.pending = {c: {} for c in range(len(chunks))}
        self.cold = {}  # chunk -> its cold result at the shared subscan
        self.done = {}  # (chunk, index) -> released result
        self.used = set(start_ids)
        self.links = []
        self.unwritten = {}  # chunk -> final ids of its cold start's bubbles the written shared subscan lacks

    def add(self, c, res):
        """Take chunk ``c``'s result; return the results whose ids are now final (latest first per chunk)."""
        if c > 0 and res.index == self.chunks[c][0]:
            self.cold[c] = res
        else:
            self.pending[c][res.index] = res
        out = []
        for cc in range(len(self.chunks)):
            if cc not in self.mapping and not self._link(cc):
                break
            ready, m = self.pending[cc], self.mapping[cc]
            for i in sorted(ready, reverse=True):
                r = ready.pop(i)
                if m is not None:  # ids the chunk's warm subscans gave new bubbles, in a fixed order
                    for k in sorted({*r.state.ids, *(int(j) for j in r.report.get("new", {}))}):
                        m[k]
                    r = relabel(r, m)
                    if len(self.chunks[cc]) > 1 and i == self.chunks[cc][1]:
                        r = drop_unwritten_ends(r, self.unwritten[cc])
                self.used.update(r.state.ids)
                self.done[(cc, i)] = r
                out.append(r)
        return out

    def _take(self):
        """The next id above every id used so far (and marks it used)."""
        i = 1 + max(self.used, default=-1)
        self.used.add(i)
        return i

    def _link(self, c):
        shared = self.chunks[c][0]
        later = self.done.get((c - 1, shared))
        if c not in self.cold or later is None:
            return False
        matches, overlaps = link_ids(self.cold[c].state, later.state)
        mapping, new = dict(matches), {}
        next_id = 1 + max(self.used, default=-1)
        for i in self.cold[c].state.ids:  # the cold start's ids; those its chunk finds later map on first sight
            if i not in mapping:
                mapping[i] = new[i] = next_id
                next_id += 1
        self.used.update(mapping.values())
        self.unwritten[c] = set(new.values())
        self.mapping[c] = _Fresh(mapping, self._take)
        self.links.append({"subscan": shared, "chunk": c, "matched": len(matches),
                           "overlap_min": min(overlaps.values(), default=None),
                           "unmatched_earlier": {str(k): v for k, v in new.items()},
                           "unmatched_later": sorted(set(later.state.ids) - set(matches.values()))})
        return True


def run_chunks(client, source, order, settings, *, step, chunks=1, start=None, times=None, on_result=None, retries=3):
    """Reconstruct subscans ``order`` (latest first) as chained tasks, in ``chunks`` chunks.

    Parameters
    ----------
    client : dask.distributed.Client or None
        None runs the tasks here, chunk after chunk.
    source : ScanFileSubscans or callable(index) -> Scan
        Where the subscans come from (a callable only in-process; on a cluster
        a scan without a file is shipped subscan by subscan).
    order : sequence of int
    settings : DynamicSettings
    step : callable(scan, state, settings, index, time) -> SubscanResult
        One subscan, module-level (picklable):
        :func:`bubsub.clients.pipeline.dynamic4d.chain.reconstruct_subscan`.
    chunks : int
    start : BubbleState, optional
        State the latest chunk starts from (a resumed run); others start cold.
    times : sequence of float, optional
    on_result : callable(SubscanResult), optional
        Called with each result once its ids are final (to write it).
    retries : int
        Tries again of a task that raised on a worker; a task lost with its
        worker is rescheduled by Dask.

    Returns
    -------
    results : list of SubscanResult
        With final ids, latest first as released.
    interrupted : bool
    links : list of dict
        Per chunk boundary: the shared subscan, matched count, smallest
        overlap, unmatched ids of either side.
    """
    parts = chunk_bounds(order, chunks)
    # a resumed run's ids, ended tracks' included, are all below its start's next_id
    linker = _Linker(parts, range(start.next_id) if start is not None else ())
    results = []
    bar = phase(f"subscans ({len(parts)} chunk{'s' if len(parts) > 1 else ''})", len(order), unit="subscan",
                enabled=settings.progress, each=True)
    worker_settings = dataclasses.replace(settings, progress=False) if client is not None else settings

    def take(c, res):
        if res.report.get("interrupted"):
            raise KeyboardInterrupt
        for r in linker.add(c, res):
            results.append(r)
            if on_result is not None:
                on_result(r)
        if not (c > 0 and res.index == parts[c][0]):
            bar.update(1, subscan=res.index, bubbles=len(res.state))

    def when(k):
        return float(times[k]) if times is not None else float(k)

    def where(k):
        return source if isinstance(source, ScanFileSubscans) else source(k)

    try:
        if client is None:
            for c, part in enumerate(parts):
                prev = start if c == 0 else None
                for k in part:
                    prev = run_subscan(step, where(k), k, prev, worker_settings, when(k))
                    take(c, prev)
        else:
            dd = distributed()
            futures, owner, token = [], {}, uuid.uuid4().hex[:8]
            for c, part in enumerate(parts):
                prev = start if c == 0 else None
                for k in part:
                    # the latest chunk first where workers are scarce: its results are final at once and gate
                    # every link
                    prev = client.submit(run_subscan, step, where(k), k, prev, worker_settings, when(k),
                                         retries=retries, priority=-c, key=f"subscan-{k:04d}-chunk{c}-{token}")
                    futures.append(prev)
                    owner[prev.key] = c
            try:
                for fut in dd.as_completed(futures):
                    take(owner[fut.key], fut.result())
            finally:
                client.cancel([f for f in futures if not f.done()])
    except KeyboardInterrupt:
        bar.close("interrupted")
        return results, True, linker.links
    except Exception:
        bar.close("failed")
        raise
    finally:
        bar.close()
    return results, False, linker.links
