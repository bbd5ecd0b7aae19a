"""The lineage of a 4D reconstruction's tracks: ``lineage.csv``, births, ends and coalescences in forward time.

``bubsub reconstruct4d`` goes backwards in time; each warm subscan's report
says what happened between it and its successor
(:mod:`bubsub.clients.pipeline.dynamic4d.detect`): ``new`` (bubbles found without a
warm start), ``coalescences`` (one bubble in the successor, two here) and
``ended`` (the successor's tracks with no bubble here). :func:`lineage_rows`
turns them into events in forward time:

* ``birth``: a track's first subscan (it ended going backwards: it entered the
  field of view through an edge, or grew from below the resolution);
* ``end``: a track's last subscan (a warm subscan found it without a warm
  start: it leaves through an edge, vanishes or was not resolved later);
* ``coalescence``: two bubbles in one subscan, one in the next (a split found
  going backwards); the merged bubble's track begins there, without a birth row.

Columns (:data:`LINEAGE_COLUMN_INFO`; ``time_s``, or ``time_subscan`` when the
scan has no times): ``event, subscan_before, subscan, time_s, parent_ids,
child_ids, reason``; ids are separated by semicolons.
"""

from __future__ import annotations

from bubsub.core.io.tables import unit_column, write_csv

__all__ = ["LINEAGE_COLUMN_INFO", "lineage_rows", "write_lineage"]


def _lineage_info(time_unit):
    """``column: (unit, meaning)`` of ``lineage.csv`` for the run's time unit."""
    info = dict(LINEAGE_COLUMN_INFO)
    meaning = info.pop("time")[1]
    info[unit_column("time", time_unit)] = ("s" if time_unit == "s" else "subscan", meaning)
    return {k: info[k] for k in ("event", "subscan_before", "subscan", unit_column("time", time_unit), "parent_ids",
                                 "child_ids", "reason")}


#: ``column: (unit, meaning)`` of ``lineage.csv`` (``time`` is ``time_s``, or ``time_subscan`` without times).
LINEAGE_COLUMN_INFO = {
    "event": ("", "birth (a track's first subscan), end (a track's last subscan) or coalescence (two bubbles in "
                  "subscan_before, one in subscan), in forward time"),
    "subscan_before": ("", "the last subscan before the event (showing the parents)"),
    "subscan": ("", "the first subscan after the event (showing the children)"),
    "time": ("s", "mid-time of subscan"),
    "parent_ids": ("", "track ids before the event, separated by semicolons (end, coalescence); empty for a birth"),
    "child_ids": ("", "track ids after the event, separated by semicolons (birth, coalescence); empty for an end"),
    "reason": ("", "what the reconstruction saw (subscans are reconstructed backwards in time: a birth is a track "
                   "that ended going backwards, an end a bubble found without a warm start)"),
}


def lineage_rows(results, time_unit):
    """Rows of ``lineage.csv`` (:data:`LINEAGE_COLUMN_INFO`), in time order.

    Each warm subscan's report says what happened between it and its successor (the next subscan of
    ``results`` in time): ``new`` (found without a warm start: the track ends here), ``coalescences`` (one
    bubble in the successor, two here) and ``ended`` (the successor's tracks that have no bubble here: they
    begin in the successor; a coalescence's parent is in its row, not a birth).
    """
    column = unit_column("time", time_unit)
    results = sorted(results, key=lambda r: r.index)
    rows = []
    for res, nxt in zip(results, results[1:] + [None]):
        after = {"subscan_before": res.index, "subscan": nxt.index if nxt is not None else "",
                 column: nxt.time if nxt is not None else ""}
        merged = {int(c["parent"]) for c in res.report.get("coalescences", [])}
        for c in res.report.get("coalescences", []):
            rows.append({"event": "coalescence", **after, "parent_ids": _ids(c["children"]),
                         "child_ids": _ids([c["parent"]]), "reason": "one bubble in the next subscan, two here "
                                                                     "(split going backwards)"})
        for i, why in sorted(res.report.get("new", {}).items(), key=lambda t: int(t[0])):
            rows.append({"event": "end", **after, "parent_ids": _ids([i]), "child_ids": "",
                         "reason": f"not in the next subscan; found here {why}"})
        for i, why in sorted(res.report.get("ended", {}).items(), key=lambda t: int(t[0])):
            if int(i) not in merged:
                rows.append({"event": "birth", **after, "parent_ids": "", "child_ids": _ids([i]),
                             "reason": f"not in the subscan before: {why}"})
    return rows


def write_lineage(path, results, time_unit):
    """Write ``lineage.csv`` and its sidecar ``lineage.csv-metadata.json`` (atomically).

    Parameters
    ----------
    path : path
    results : sequence of SubscanResult
        The run's subscans (any order).
    time_unit : {"s", "subscan"}

    Returns
    -------
    list of dict
        The rows written (:func:`lineage_rows`).
    """
    info = _lineage_info(time_unit)
    rows = lineage_rows(results, time_unit)
    write_csv(path, rows, list(info), describe=info, title="bubble track events of a bubsub reconstruct4d run")
    return rows


def _ids(ids):
    return ";".join(str(int(i)) for i in ids)
