"""Slabs of detector rows: a tall parallel-beam scan reconstructed piece by piece.

In a parallel-beam scan whose detector rows are perpendicular to the
rotation axis, each row sees one slice of the sample, so the scan splits
exactly into slabs of rows. Each slab is one task:

1. it reads only its rows from the scan file (:func:`bubsub.core.io.scanfile.read_scan`
   with ``rows=``: HDF5 hyperslabs; no process holds the whole scan), or cuts
   them from a scan in memory (:meth:`Scan.row_window`, a 4D subscan): the rows
   it *owns* (its core) and a *halo* of rows above and below, at least the
   largest bubble's radius wide (:func:`slab_scan`);
2. it reconstructs them with the full pipeline (:func:`~bubsub.clients.pipeline.reconstruct.reconstruct`)
   in coordinates centred on the rows read (:meth:`ScanGeometry.translated`),
   so every stage sees an ordinary, smaller scan: bubbles reaching into the
   halo are fitted there against the data they really produce, with the
   neighbours' bubbles of the halo fitted beside them as known signal;
3. it keeps, in world coordinates, every bubble with its centroid's
   distance to the rows read.

:func:`stitch` then keeps each bubble once: the bubbles whose centroid lies
in their slab's core, of two such bubbles of neighbouring slabs at the same
place (a centroid on a seam) the one further from its slab's edge, and a
bubble whose centroid fell into the halo of both slabs (claimed by neither)
from the slab that saw it whole. A bubble is therefore never lost,
duplicated or cut at a seam as long as the halo holds the bubbles whose
centres are in the core (the report counts the kept bubbles that reach a
slab's read edge, ``seam_cut``; zero says the halo was wide enough).

Bubbles of known identity (the warm starts of a 4D subscan, each with its
track id) are fitted slab by slab with :func:`fit_known`: each slab fits the
bubbles whose starting centroid lies in its rows read, and keeps those whose
starting centroid lies in its core. Ownership by the starting centroid needs
no matching and gives every bubble exactly one slab however far its fit moves
it: the cores partition the detector and each lies within its rows read.

The slabs run one after another in this process (``client=None``) or as
Dask tasks (:func:`bubsub.clients.cluster.engine.run_tasks`); each finished
slab is written to ``OUT/slabs/`` at once, so ``resume=True`` continues
after a crash or Ctrl-C from the slabs already done. Memory is one slab's,
whatever the number of slabs.

Three modules share the work, all on one slab layout (core, rows read,
origin, ownership heights) that :mod:`.slab_layout` defines with the plan
and the halo; :mod:`.slab_stitch` holds the ownership rules (stitching, and
the fit of known bubbles); this module runs the slabs, writes and reads
their checkpoints and makes the report. The other two modules' entry
points are importable from here too (this module's ``__all__``).

Cone beam: the rows of a cone-beam detector are not slices of the sample
(the rays diverge), so :func:`check_slab_geometry` refuses it; such a scan
is reconstructed whole.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bubsub.core.io.atomic import atomic_path
from bubsub.core.projection.mesh import Mesh
from bubsub.core.projection.subdivision import SubdivisionSurface

from bubsub.clients.cluster.engine import run_tasks
from bubsub.clients.pipeline.inputs.checks import check_settings
from bubsub.clients.pipeline.inputs.fov import fov_report
from bubsub.clients.pipeline.phase_report import merged_projector_report
from bubsub.clients.pipeline.reconstruct import Reconstruction, ReconstructionSettings, reconstruct
from bubsub.clients.pipeline.static.resolution import level_counts
# the slabs' layout and stitching, named here too: this module is where the other modules find the slabs
from bubsub.clients.pipeline.regions.slab_layout import (SLAB_PIXELS, WHOLE_SCAN_SLABS, Slab, SlabResult, auto_slabs,
                                                         check_slab_geometry, default_slab_rows, estimate_halo,
                                                         halo_rows, is_scan, known_halo, moved, plan_slabs,
                                                         scan_geometry, slab_bounds, slab_count, slab_origin, slab_scan)
from bubsub.clients.pipeline.regions.slab_stitch import (core_preview, fit_known, rows_entry, slab_totals, stitch,
                                                         stitch_previews)
from bubsub.clients.progress import phase
from bubsub.clients.remote.jobs import remote_projectors
from bubsub.clients.pipeline.results.outputs import json_default

__all__ = ["Slab", "SlabResult", "plan_slabs", "check_slab_geometry", "slab_origin", "default_slab_rows",
           "auto_slabs", "slab_count", "estimate_halo", "known_halo", "halo_rows", "slab_scan", "slab_bounds", "run_slab", "stitch",
           "stitch_previews", "fit_known", "slab_totals", "reconstruct_slabs", "SLAB_PIXELS", "WHOLE_SCAN_SLABS",
           "OBJECTIVE_NOTE"]

_FORMAT = 1


def run_slab(source, slab, settings, bubble_contrast=None, server=None, token=None, signal_checked=False):
    """Reconstruct one slab (a task: module-level, picklable arguments, small result).

    Parameters
    ----------
    source : str, Path or Scan
        The scan file, of which only the slab's rows are read, or the scan in memory.
    slab : Slab
    settings : ReconstructionSettings
    bubble_contrast : float, optional
        As :func:`read_scan`'s.
    server, token : str, optional
        A projector server to fit against (each slab a fitting job of its own).
    signal_checked : bool
        The scan's bubble signal was checked whole: the slab's is not checked again
        (:func:`~bubsub.clients.pipeline.reconstruct.reconstruct`).

    Returns
    -------
    SlabResult
    """
    local, origin = slab_scan(source, slab, bubble_contrast)
    with remote_projectors(server, token, supersampling=settings.supersampling) as factory:
        rec = reconstruct(local, settings, projector_factory=factory, signal_checked=signal_checked)
    report = dict(rec.report, origin_mm=origin.tolist(), core_rows=list(slab.core), read_rows=list(slab.read))
    part, extent = core_preview(rec, local.geometry, slab, origin)
    return SlabResult(slab, [moved(s, origin) for s in rec.surfaces], report, part, extent)


# -- checkpoints ------------------------------------------------------------------------------------------
def slab_key(scan_path, slab, settings):
    """What a finished slab's checkpoint must match to be reused by ``resume``: the scan file (path, size,
    modification time), the slab's rows and every setting."""
    p = Path(scan_path).resolve()
    st = p.stat()
    doc = {"scan": str(p), "size": st.st_size, "mtime_ns": st.st_mtime_ns, "slab": [slab.core, slab.read,
           slab.detector_rows], "settings": {k: v for k, v in vars(settings).items() if k != "progress"},
           "format": _FORMAT}
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()


def write_slab(path, result, key):
    """Write a :class:`SlabResult` atomically (``.npz``: control meshes, levels, report as JSON)."""
    surfaces = result.surfaces
    arrays = {
        "key": np.array(key),
        "slab": np.array([result.slab.index, *result.slab.core, *result.slab.read, result.slab.detector_rows]),
        "report": np.array(json.dumps(result.report, default=json_default)),
        "n_vertices": np.array([len(s.vertices) for s in surfaces], dtype=np.int64),
        "n_faces": np.array([len(s.control_faces) for s in surfaces], dtype=np.int64),
        "levels": np.array([s.levels for s in surfaces], dtype=np.int64),
        "attenuation": np.array([s.attenuation for s in surfaces], dtype=float),
        "vertices": np.concatenate([s.vertices for s in surfaces]) if surfaces else np.zeros((0, 3)),
        "faces": np.concatenate([s.control_faces for s in surfaces]) if surfaces else np.zeros((0, 3), np.int64),
    }
    if result.preview is not None:
        arrays["preview"], arrays["preview_extent"] = result.preview, np.asarray(result.preview_extent, dtype=float)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def read_slab(path, key=None):
    """A checkpoint of :func:`write_slab`, or None when it is missing, unreadable or was made with another key."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if key is not None and str(z["key"]) != key:
                return None
            idx, c0, c1, r0, r1, n_rows = (int(x) for x in z["slab"])
            report = json.loads(str(z["report"]))
            v_end, f_end = np.cumsum(z["n_vertices"]), np.cumsum(z["n_faces"])
            surfaces = []
            for k in range(len(v_end)):
                v = z["vertices"][v_end[k] - z["n_vertices"][k]:v_end[k]]
                f = z["faces"][f_end[k] - z["n_faces"][k]:f_end[k]]
                surfaces.append(SubdivisionSurface(Mesh(v, f, float(z["attenuation"][k])), int(z["levels"][k])))
            preview = np.array(z["preview"]) if "preview" in z else None
            extent = tuple(float(x) for x in z["preview_extent"]) if "preview_extent" in z else None
    except (OSError, ValueError, KeyError):
        return None
    return SlabResult(Slab(idx, (c0, c1), (r0, r1), n_rows), surfaces, report, preview, extent)


# -- the whole scan ---------------------------------------------------------------------------------------
def reconstruct_slabs(source, settings=None, *, slabs=None, halo=None, client=None, out=None, resume=False,
                      server=None, token=None, bubble_contrast=None, signal_checked=False):
    """Reconstruct a scan slab by slab and stitch the bubbles (see the module docstring).

    Parameters
    ----------
    source : str, Path or Scan
        The scan file, of which each slab reads its rows, or a scan in memory (a 4D subscan), which every
        task receives whole (on a cluster, give the file).
    settings : ReconstructionSettings, optional
        Each slab's.
    slabs : int, optional
        Number of slabs; default :func:`auto_slabs`.
    halo : int, optional
        Halo rows; default :func:`estimate_halo`.
    client : dask.distributed.Client, optional
        Run the slabs as tasks on its cluster; None runs them here, one after the other.
    out : str or Path, optional
        Folder whose ``slabs/`` subfolder receives each finished slab's checkpoint (a scan file only: the
        checkpoints' key names it).
    resume : bool
        Reuse the checkpoints in ``out/slabs`` made with the same scan, rows and settings.
    server, token : str, optional
        Fit every slab against this projector server.
    bubble_contrast : float, optional
    signal_checked : bool
        ``source``'s bubble signal was checked whole (a subscan of a checked dynamic scan): the slabs' are
        not checked again; otherwise each slab checks its rows.

    Returns
    -------
    Reconstruction
        ``report["slabs"]`` has each slab's rows, bubbles, seconds and stop reason;
        ``report["stitch"]`` :func:`stitch`'s summary.
    """
    s = settings or ReconstructionSettings()
    t0 = time.perf_counter()
    geometry = scan_geometry(source)
    check_settings(s, geometry.ndim)
    check_slab_geometry(geometry)
    if s.holdout is not None:
        raise ValueError("--holdout is not available with slabs; reconstruct the scan whole (--slabs 1)")
    if out is not None and is_scan(source):
        raise ValueError("slab checkpoints (out=) need a scan file: their key is the file's")
    if halo is None:
        halo = estimate_halo(source, geometry, s, bubble_contrast)
    if slabs is None:
        slabs = auto_slabs(geometry, halo)
    plan = plan_slabs(geometry.det_rows, slabs, halo)
    folder = None if out is None else Path(out) / "slabs"
    keys = [None if folder is None else slab_key(source, sl, s) for sl in plan]
    results = [None] * len(plan)
    if resume and folder is not None:
        for k, sl in enumerate(plan):
            results[k] = read_slab(folder / f"slab_{sl.index:03d}.npz", keys[k])
    todo = [k for k in range(len(plan)) if results[k] is None]
    task_settings = replace(s, progress=s.progress and client is None and len(plan) == 1)
    with phase(f"slabs ({len(plan)} of {plan[0].core[1] - plan[0].core[0]} rows, halo {halo})", len(plan),
               unit="slab", enabled=s.progress) as bar:
        bar.update(len(plan) - len(todo))

        def done(i, res):
            k = todo[i]
            results[k] = res
            if folder is not None:
                write_slab(folder / f"slab_{plan[k].index:03d}.npz", res, keys[k])
            bar.update(1, bubbles=sum(len(r.surfaces) for r in results if r is not None))

        task_source = source if is_scan(source) else str(source)
        run_tasks(client, run_slab, [(task_source, plan[k], task_settings, bubble_contrast, server, token,
                                      signal_checked) for k in todo], on_result=done)
    surfaces, summary = stitch(results, geometry)
    preview, extent = stitch_previews(results)
    return Reconstruction(surfaces, _report(results, surfaces, summary, geometry, s, halo, len(todo),
                                            time.perf_counter() - t0, fov_report(geometry)), preview, extent)


#: ``report.json``'s word on the objectives of a slabbed fit.
OBJECTIVE_NOTE = "objectives are sums over the slabs' own objectives (halo rows counted in two slabs)"

_SUMMED = ("iterations", "evaluations", "final_objective", "initial_objective", "bubbles_initial", "bubbles_dropped",
           "seconds_initialisation", "seconds_fit")


def _report(results, surfaces, summary, geometry, settings, halo, computed, seconds, fov):
    """``report.json`` of a slabbed reconstruction."""
    per_slab = []
    for res in results:
        r = res.report
        per_slab.append({**rows_entry(res.slab), "bubbles": r["bubbles"], "stop_reason": r.get("stop_reason"),
                         "seconds_total": r.get("seconds_total"), "seconds_parts": r.get("seconds_parts"),
                         "cpu_seconds_parts": r.get("cpu_seconds_parts"), "iterations": r.get("iterations"),
                         "final_objective": r.get("final_objective"), "fit_levels": r.get("fit_levels"),
                         "preview": r.get("preview")})
    parts, cpu = {}, {}
    for res in results:
        for name, v in (res.report.get("seconds_parts") or {}).items():
            parts[name] = parts.get(name, 0.0) + v
        for name, v in (res.report.get("cpu_seconds_parts") or {}).items():
            cpu[name] = cpu.get(name, 0.0) + v
    report = slab_totals([res.report for res in results], _SUMMED)
    report.update({
        "bubbles": len(surfaces),
        "dimension": 3,
        "subdivision_levels": level_counts(surfaces),
        "slabs": per_slab,
        "slab_halo_rows": halo,
        "slabs_computed": computed,
        "stitch": summary,
        "objective_note": OBJECTIVE_NOTE,
        "seconds_total": seconds,
        "seconds_parts": parts,
        "cpu_seconds_parts": cpu,
        "field_of_view_mm": fov,
        "preview": _stitched_preview(results),
        "projections_used": geometry.n_angles,
        "validity": _merged_validity(results),
        "projector": merged_projector_report([res.report.get("projector") for res in results]),
        "settings": {k: v for k, v in vars(settings).items() if k != "progress"},
    })
    return report


def _stitched_preview(results):
    """The slabs' previews in one entry: the coarsest voxel (each slab chooses its own for its bubbles,
    :func:`.preview.voxel_for_bubbles`; the coarsest is the resolution every slab's contacts rest on, and
    ``bubsub analyse``'s default contact gap), and whether any slab made its preview finer; None for
    reports without it."""
    previews = [res.report.get("preview") for res in results]
    if not previews or any(p is None for p in previews):
        return None
    return {"voxel_mm": max(p["voxel_mm"] for p in previews),
            "finer_for_bubbles": any(p["finer_for_bubbles"] for p in previews)}


def _merged_validity(results):
    found = [v for res in results for v in (res.report.get("validity") or {}).get("violations_remaining", [])]
    return {"violations_found": [], "actions": [], "violations_remaining": found,
            "dropped": sum((res.report.get("validity") or {}).get("dropped", 0) for res in results)}
