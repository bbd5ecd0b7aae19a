"""Files of a 4D reconstruction: one folder per subscan, tracks.csv, report.json, plots.

``DIR/subscan_NNNN/`` holds what ``bubsub reconstruct`` writes (bubble ids =
track ids); it is written as ``DIR/.subscan_NNNN.partial`` and renamed when
complete, so a folder with the final name is always complete (``--resume``
trusts it). ``tracks.csv`` (:func:`write_tracks`, with its CSVW sidecar
``tracks.csv-metadata.json``, columns :func:`tracks_info`) has one row per
(subscan, bubble):

=====================  ======  =============================================
column                 unit    meaning
=====================  ======  =============================================
subscan                        subscan index in the scan
time_s | time_subscan  s       mid-time of the subscan (``/exchange/time``);
                               ``time_subscan``: the subscan index when the scan
                               has no times
bubble_id                      track id (kept through time)
centroid_x_mm, _y_mm   mm      centroid of the area (solid) the refined
                               outline (surface) encloses
[, centroid_z_mm]
area_mm2 | volume_mm3  mm^2|3  2D area, 3D volume
perimeter_mm |         mm|mm^2 2D perimeter, 3D surface area (the smooth
surface_area_mm2               surface's, as in ``bubsub analyse``)
equivalent_diameter_mm mm      of the disc (ball) of equal area (volume)
truncated                      the bubble crosses the edge of the field of
                               view: its whole-size columns above are empty
area_in_fov_mm2 |      mm^2|3  the part inside the field of view
volume_in_fov_mm3
=====================  ======  =============================================

The last two columns are there when the subscans' reports have their field
of view (every ``bubsub reconstruct4d`` run writes it); see
:func:`bubsub.clients.pipeline.inputs.fov.fov_columns`.

``lineage.csv`` (:func:`bubsub.clients.pipeline.dynamic4d.lineage.write_lineage`, with
its CSVW sidecar) lists the tracks' births, ends and coalescences in forward
time.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from bubsub.core.io.atomic import atomic_path, atomic_write_text
from bubsub.core.io.meshio import read_ply, read_polygons_json
from bubsub.core.io.tables import BUBBLE_COLUMN_INFO, unit_column, write_table
from bubsub.core.analysis.shape import bubble_table
from bubsub.core.projection.subdivision import SubdivisionSurface

from bubsub.clients.pipeline.dynamic4d.chain import BubbleState, SubscanResult
from bubsub.clients.pipeline.dynamic4d.lineage import write_lineage
from bubsub.clients.pipeline.results.outputs import json_default, write_outputs
from bubsub.clients.pipeline.results.figures import subplots
from bubsub.clients.pipeline.inputs.fov import FOV_COLUMN_INFO, fov_columns
from bubsub.clients.pipeline.reconstruct import Reconstruction

__all__ = ["subscan_dir", "write_subscan", "read_subscan_result", "complete_subscans", "track_rows",
           "tracks_info", "write_tracks", "write_summary"]


def subscan_dir(out, index):
    """``out/subscan_NNNN``."""
    return Path(out) / f"subscan_{int(index):04d}"


def write_subscan(out, result, ndim, scan_path=None):
    """Write one subscan's folder atomically (a partial folder renamed when complete).

    Returns
    -------
    pathlib.Path
        The subscan's folder.
    """
    final = subscan_dir(out, result.index)
    partial = Path(out) / f".{final.name}.partial"
    if partial.exists():
        shutil.rmtree(partial)
    report = dict(result.report, dimension=ndim, levels=list(result.state.levels), track_ids=list(result.state.ids))
    rec = Reconstruction(result.state.surfaces(), report, result.preview, result.preview_extent,
                         ids=list(result.state.ids))
    write_outputs(partial, rec, scan_path=scan_path)
    if final.exists():  # a stale folder of an earlier run, replaced by the complete new one
        shutil.rmtree(final)
    os.replace(partial, final)
    return final


def read_subscan_result(out, index, attenuation):
    """A completed subscan folder back as a :class:`~bubsub.clients.pipeline.dynamic4d.chain.SubscanResult`."""
    d = subscan_dir(out, index)
    report = json.loads((d / "report.json").read_text())
    if report["dimension"] == 3:
        items, ids = read_ply(d / "control.ply", attenuation=attenuation, with_ids=True)
    else:
        items, ids = read_polygons_json(d / "control.json", attenuation=attenuation, with_ids=True)
    levels = report.get("levels", 2)  # per bubble, or one number for all
    levels = [int(levels)] * len(items) if np.isscalar(levels) else [int(n) for n in levels]
    if len(levels) != len(items):
        raise ValueError(f"{d / 'report.json'}: 'levels' has {len(levels)} entries for {len(items)} bubbles")
    state = BubbleState.from_surfaces(ids, [SubdivisionSurface(m, n) for m, n in zip(items, levels)], attenuation)
    for k in ("dimension", "levels", "track_ids", "files", "scan"):
        report.pop(k, None)
    ended = tuple(int(i) for i in report.get("ended", {}))
    return SubscanResult(int(index), float(report["time"]), state, ended, report)


def complete_subscans(out):
    """Indices of the complete subscan folders in ``out`` (sorted)."""
    out = Path(out)
    if not out.is_dir():
        return []
    found = []
    for p in out.iterdir():
        if p.is_dir() and p.name.startswith("subscan_") and (p / "report.json").is_file():
            try:
                found.append(int(p.name[len("subscan_"):]))
            except ValueError:
                continue
    return sorted(found)


def time_column(time_unit):
    """The ``tracks.csv`` column of the subscans' mid-times: ``time_s``, or ``time_subscan`` without times."""
    return unit_column("time", time_unit)


def track_rows(results, time_unit):
    """Rows of ``tracks.csv`` (see the module docstring), in time order."""
    column = time_column(time_unit)
    results = sorted(results, key=lambda r: r.index)
    # the field-of-view columns when every subscan's report has its field of view (one set of columns)
    with_fov = bool(results) and all(r.report.get("field_of_view_mm") is not None for r in results)
    rows = []
    for res in results:
        fine = [s.fine() for s in res.state.surfaces()]
        table = bubble_table(fine, list(res.state.ids))
        if with_fov and fine:
            # unobserved control vertices are per subscan's fit (in its folder's bubbles.csv), not per track
            fov_columns(table, fine, {k: v for k, v in res.report.items() if k != "unobserved_control_vertices"})
        for row in table:
            bid = row.pop("id")
            rows.append({"subscan": res.index, column: res.time, "bubble_id": bid, **row})
    return rows


def tracks_info(time_unit, columns=None):
    """``column: (unit, meaning)`` of ``tracks.csv``: the subscan, its time, the track id and the columns of
    ``bubbles.csv`` (:data:`~bubsub.core.io.tables.BUBBLE_COLUMN_INFO`, and those of the field of view),
    restricted to ``columns`` (the rows' keys) when given."""
    when = "mid-time of the subscan" if time_unit == "s" else "subscan index (the scan has no times)"
    info = {"subscan": ("", "subscan index in the scan"), time_column(time_unit): (time_unit, when),
            "bubble_id": ("", "track id (kept through time; the id of the subscan folder's bubbles)"),
            **{k: v for k, v in BUBBLE_COLUMN_INFO.items() if k != "id"},
            **{k: v for k, v in FOV_COLUMN_INFO.items() if k != "unobserved_control_vertices"}}
    return info if columns is None else {c: info[c] for c in columns}


def write_tracks(path, results, time_unit, rows=None):
    """Write ``tracks.csv`` and its sidecar (atomically); the one place its columns are decided. ``rows``:
    :func:`track_rows` of ``results`` when already made."""
    rows = track_rows(results, time_unit) if rows is None else rows
    columns = list(rows[0]) if rows else ["subscan", time_column(time_unit), "bubble_id"]
    return write_table(path, rows, tracks_info(time_unit, columns),
                       title="bubble tracks of a bubsub reconstruct4d run: one row per subscan and bubble")[0]


def write_summary(out, results, *, layout, time_unit, settings, engine="local", workers=1, interrupted=False,
                  baseline=None, chunks=1, chunk_links=()):
    """Write ``tracks.csv``, ``report.json``, ``growth.png`` and ``mse.png`` for the completed subscans."""
    out = Path(out)
    results = sorted(results, key=lambda r: r.index)
    # the rows once: each subscan's bubble table and field-of-view columns are a few seconds of a run's summary
    rows = track_rows(results, time_unit)
    write_tracks(out / "tracks.csv", results, time_unit, rows)
    lineage = write_lineage(out / "lineage.csv", results, time_unit)
    per = [dict(r.report) for r in results]
    ended = [i for r in results for i in r.ended]
    warm = [p["seconds"] for p in per if p.get("start") == "warm"]
    cold = [p["seconds"] for p in per if p.get("start") == "cold"]
    report = {
        "engine": engine, "workers": workers, "chunks": chunks, "chunk_links": list(chunk_links),
        "interrupted": interrupted,
        "projections_per_subscan": layout.per_subscan, "subscans_in_scan": layout.n_subscans,
        "projections_ignored": layout.leftover,
        "subscans_selected": [layout.selected.start, layout.selected.stop],
        "subscans_complete": len(results), "time_unit": time_unit,
        "settings": {k: v for k, v in settings.__dict__.items() if k != "progress"},
        "totals": {
            "seconds": float(sum(p["seconds"] for p in per)),
            "seconds_cold": float(sum(cold)), "seconds_warm_median": float(np.median(warm)) if warm else None,
            "warm_to_cold_time": float(np.median(warm) / sum(cold)) if warm and cold else None,
            "iterations": int(sum(p["iterations"] or 0 for p in per)),
            "tracks": len({i for r in results for i in r.state.ids} | set(ended)),
            "tracks_ended": len(ended), "subscans_diverged": sum(bool(p.get("diverged")) for p in per),
            "lineage": {e: sum(r["event"] == e for r in lineage) for e in ("birth", "end", "coalescence")},
        },
        "subscans": per,
    }
    atomic_write_text(out / "report.json", json.dumps(report, indent=2, default=json_default))
    if results:
        plot_growth(out / "growth.png", rows, time_unit)
        plot_mse(out / "mse.png", per)
    return report


def plot_growth(path, rows, time_unit):
    """Equivalent diameter against time per bubble, and the size distribution at up to four times."""
    column = time_column(time_unit)

    fig, (a, b) = subplots(1, 2, figsize=(11, 4.2), dpi=100)
    rows = [r for r in rows if r["equivalent_diameter_mm"] != ""]  # a truncated bubble has no whole size
    by_id = {}
    for r in rows:
        by_id.setdefault(r["bubble_id"], []).append((r[column], r["equivalent_diameter_mm"]))
    for pts in by_id.values():
        t, d = np.array(sorted(pts)).T
        a.plot(t, d, lw=0.8, marker=".", ms=3)
    a.set_xlabel(f"time ({time_unit})")
    a.set_ylabel("equivalent diameter (mm)")
    a.set_title(f"{len(by_id)} bubble tracks", fontsize=10)
    times = sorted({r[column] for r in rows})
    pick = [times[int(round(i))] for i in np.linspace(0, len(times) - 1, min(4, len(times)))]
    for t in dict.fromkeys(pick):
        d = [r["equivalent_diameter_mm"] for r in rows if r[column] == t]
        b.hist(d, bins=12, histtype="step", label=f"t = {t:.3g} {time_unit}")
    b.set_xlabel("equivalent diameter (mm)")
    b.set_ylabel("bubbles")
    b.legend(fontsize=8)
    b.set_title("size distribution", fontsize=10)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")


def plot_mse(path, per_subscan):
    """Held-out projection MSE per subscan: BubSub and, where run, the voxel baseline (paper fig. 6)."""
    fig, ax = subplots(figsize=(6.5, 4), dpi=100)
    sub = [p["subscan"] for p in per_subscan]
    for key, label in (("holdout_mse", "BubSub"), ("voxel_holdout_mse", "voxel (BB, 30 it., x >= 0)")):
        vals = [p.get(key) for p in per_subscan]
        if any(v is not None for v in vals):
            ax.plot(sub, [np.nan if v is None else v for v in vals], marker="o", ms=3, label=label)
    ax.set_xlabel("subscan")
    ax.set_ylabel("held-out projection MSE")
    ax.set_yscale("log")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    else:
        ax.set_title("no held-out projections (use --holdout)", fontsize=10)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
