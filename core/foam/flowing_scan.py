"""The scan of a flowing foam (:mod:`bubsub.core.foam.flowing`), its events and its simulation folder.

The scan (:func:`simulate_flowing`) rotates continuously, ``180`` degrees per
subscan, and each projection sees the foam at its own time through exact
sub-ray chords of the ellipsoids (:func:`~bubsub.core.foam.ellipsoids.project_ellipsoids`),
not through the subdivision meshes a reconstruction fits. :func:`flowing_events`
lists when bubbles enter, leave, vanish and coalesce, and :func:`write_flowing`
writes the simulation folder ``bubsub reconstruct4d`` and ``bubsub bench
dynamic`` read.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bubsub.core.foam.checks import count
from bubsub.core.foam.column import TRUTH_COLUMN_INFO, truth_grid
from bubsub.core.foam.ellipsoids import ellipsoid_mesh, project_cylinder, project_ellipsoids, shape_matrices
from bubsub.core.foam.flowing import FlowingFoam
from bubsub.core.foam.simulate import add_poisson_noise
from bubsub.core.io.atomic import atomic_write_text
from bubsub.core.io.meshio import write_ply
from bubsub.core.io.scanfile import Scan, write_scan
from bubsub.core.io.tables import write_csv
from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.projection.mesh import equivalent_radius

__all__ = ["flowing_geometry", "projection_times", "simulate_flowing", "EVENT_COLUMN_INFO", "flowing_events",
           "truth_rows", "write_flowing"]


def flowing_geometry(foam, projections_per_subscan=40):
    """Continuous rotation: ``projections_per_subscan`` views per 180 degrees, subscan after subscan."""
    p = count("projections_per_subscan", projections_per_subscan)
    n = int(round(foam.duration)) * p
    c = foam.column
    return ScanGeometry.parallel(np.arange(n) * np.pi / p, pixel_size=c.pixel_size, cols=c.cols, rows=c.rows)


def projection_times(n_projections, projections_per_subscan):
    """(n,) time of each projection in subscans: ``(j + 0.5) / P``."""
    return (np.arange(n_projections) + 0.5) / projections_per_subscan


def simulate_flowing(foam, *, projections_per_subscan=40, photons=1e4, supersampling=2, noise_seed=None,
                     seconds_per_projection=0.01):
    """The dynamic scan of a flowing foam, each projection at its own time.

    Parameters
    ----------
    foam : FlowingFoam
    projections_per_subscan : int
        Views per 180 degrees (one subscan).
    photons : float or None
        I0 of the Poisson noise; None: noise-free.
    supersampling : int
        Sub-rays per pixel and axis.
    noise_seed : int, optional
        Defaults to the foam's seed.
    seconds_per_projection : float
        ``/exchange/time`` step, s.

    Returns
    -------
    Scan
        ``(n_projections, rows, cols)`` line integrals in acquisition order, with ``time``,
        ``projections_per_subscan`` and the cylinder's noise-free projection as ``background``.
    """
    if not isinstance(foam, FlowingFoam):
        raise ValueError(f"foam must be a FlowingFoam, got {type(foam).__name__}")
    c = foam.column
    geometry = flowing_geometry(foam, projections_per_subscan)
    k = count("supersampling", supersampling)
    background = project_cylinder(geometry, c.radius, c.z_range, c.liquid_attenuation, k)
    clean = background.copy()
    t = projection_times(geometry.n_angles, projections_per_subscan)
    for view in range(geometry.n_angles):
        st = foam.at(t[view])
        seen = st.visible
        if seen.any():
            project_ellipsoids(geometry[view:view + 1], st.centres[seen], st.axes[seen], st.rotations[seen],
                               c.contrast, k, out=clean[view:view + 1])
    seed = c.seed if noise_seed is None else int(noise_seed)
    data = clean if photons is None else add_poisson_noise(clean, photons, seed)
    attrs = {"simulated": 1, "method": "analytic", "phantom": "flowing3d", "dynamic": 1,
             "photons": 0.0 if photons is None else float(photons), "phantom_seed": c.seed,
             "supersampling": k, "flow_px_per_subscan": foam.velocity / c.pixel_size}
    if photons is not None:
        attrs["noise_seed"] = seed
    scan = Scan(data=np.asarray(data, dtype=np.float32), geometry=geometry,
                background=background.astype(np.float32), bubble_contrast=c.contrast, attrs=attrs)
    scan.time = np.arange(geometry.n_angles) * float(seconds_per_projection)
    scan.projections_per_subscan = int(projections_per_subscan)
    return scan


#: ``column: (unit, meaning)`` of ``events.csv``.
EVENT_COLUMN_INFO = {
    "event": ("", "enter (through the bottom row), exit (through the top row), vanish (shrinks to nothing) or "
                  "coalesce (the parents merge into the child)"),
    "id": ("", "the bubble the event happens to (coalesce: the child)"),
    "parents": ("", "coalesce: the two merging ids, separated by a semicolon; empty otherwise"),
    "time_subscans": ("subscan", "when it happens, in subscans from the scan's start (subscan k's mid-time is "
                                 "k + 0.5); enter / exit: from when it reaches / no longer reaches into the rows"),
    "seconds": ("s", "the same time in seconds"),
    "subscan": ("", "the first subscan whose truth shows the event's outcome"),
    "in_fov": ("1", "1 if the bubble (vanish: just before; coalesce: the child) is in the detector's rows"),
}


def flowing_events(foam, projections_per_subscan, seconds_per_projection=0.01):
    """Enter, exit, vanish and coalesce events during the scan, in time order.

    Enter and exit are found between consecutive projections and bisected to
    1e-6 subscans: the time from which the bubble reaches into / no longer
    reaches into the rows.

    Returns
    -------
    list of dict
        Rows of :data:`EVENT_COLUMN_INFO`.
    """
    p = int(projections_per_subscan)
    times = projection_times(int(round(foam.duration)) * p, p)
    unit = seconds_per_projection * p

    def row(event, bid, t, in_fov, parents=""):
        return {"event": event, "id": int(bid), "parents": parents, "time_subscans": float(t),
                "seconds": float(t * unit), "subscan": int(np.ceil(t - 0.5)), "in_fov": int(in_fov)}

    def crossing(b, lo, hi):
        """The time in (lo, hi] at which bubble b's visibility changes, bisected to 1e-6 subscans."""
        was = visible(b, lo)
        while hi - lo > 1e-6:
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if visible(b, mid) == was else (lo, mid)
        return hi

    def visible(b, t):
        st = foam.at(t)
        k = np.flatnonzero(st.ids == b)
        return bool(len(k) and st.fraction_in_fov[k[0]] > 0)

    rows = []
    children = {m["child"] for m in foam.merges}
    before = foam.at(times[0])
    seen = set(before.ids[before.visible].tolist())
    for t_prev, t in zip(times[:-1], times[1:]):
        st = foam.at(t)
        now = set(st.ids[st.visible].tolist())
        exists = set(st.ids.tolist())
        for b in sorted(now - seen):
            if b not in children:
                rows.append(row("enter", b, crossing(b, t_prev, t), True))
        for b in sorted(seen - now):
            if b in exists:
                rows.append(row("exit", b, crossing(b, t_prev, t), True))
        seen = now
    for b in np.flatnonzero(np.isfinite(foam.vanish_time)):
        tv = foam.vanish_time[b]
        st = foam.at(tv * (1 - 1e-9))
        k = np.flatnonzero(st.ids == b)
        rows.append(row("vanish", b, tv, bool(len(k) and st.fraction_in_fov[k[0]] > 0)))
    for m in foam.merges:
        st = foam.at(m["time"])
        k = np.flatnonzero(st.ids == m["child"])
        rows.append(row("coalesce", m["child"], m["time"], bool(st.fraction_in_fov[k[0]] > 0),
                        f"{m['parents'][0]};{m['parents'][1]}"))
    return sorted(rows, key=lambda r: (r["time_subscans"], r["id"]))


def truth_rows(state, fov_half_height):
    """Rows of :data:`~bubsub.core.foam.column.TRUTH_COLUMN_INFO` of a state's visible bubbles (id = bubble id)."""
    vis = state.select(state.visible)
    vol = vis.volumes
    ez = np.sqrt(shape_matrices(vis.axes, vis.rotations)[:, 2, 2])
    z, h = vis.centres[:, 2], float(fov_half_height)
    rows = []
    for n, b in enumerate(vis.ids):
        rows.append({"id": int(b), **{f"centre_{a}_mm": float(vis.centres[n, i]) for i, a in enumerate("xyz")},
                     **{f"semi_axis_{k + 1}_mm": float(vis.axes[n, k]) for k in range(3)},
                     **{f"rotation_{i + 1}{j + 1}": float(vis.rotations[n, i, j]) for i in range(3) for j in range(3)},
                     "volume_mm3": float(vol[n]), "volume_in_fov_mm3": float(vol[n] * vis.fraction_in_fov[n]),
                     "equivalent_diameter_mm": 2.0 * equivalent_radius(vol[n], 3),
                     "cut_top": int(abs(z[n] - h) < ez[n]), "cut_bottom": int(abs(z[n] + h) < ez[n])})
    return rows


def write_flowing(out, foam, scan, *, truth_subdivisions=3, grid_voxel=None, seconds_per_projection=0.01):
    """Write a flowing foam's simulation folder.

    ``scan.h5`` (all projections in acquisition order, ``projections_per_subscan``,
    ``/exchange/time``); per subscan ``k`` at its mid-time, ``truth/subscan_kkkk.ply``
    (meshes of the bubbles in the rows, ``bubble_id`` = bubble id) and
    ``truth/subscan_kkkk.csv`` (their analytic ellipsoids, columns of
    :data:`~bubsub.core.foam.column.TRUTH_COLUMN_INFO`); ``events.csv``
    (:data:`EVENT_COLUMN_INFO`); ``phantom.json`` (``truth`` names the folder,
    ``column`` the field of view, ``flowing`` the dynamics).

    Returns
    -------
    files : list of Path
    meta : dict
        The contents of ``phantom.json``.
    """
    out = Path(out)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    c = foam.column
    p = int(scan.projections_per_subscan)
    n_sub = scan.geometry.n_angles // p
    h = c.fov_half_height
    files = [write_scan(out / "scan.h5", scan)]
    ids_seen, counts = set(), []
    for k in range(n_sub):
        st = foam.at(k + 0.5)
        vis = st.select(st.visible)
        rows = truth_rows(st, h)
        meshes, template = [], None
        for n in range(len(vis.ids)):
            template = ellipsoid_mesh(vis.centres[n], vis.axes[n], vis.rotations[n], c.contrast, truth_subdivisions,
                                      template=template)
            meshes.append(template)
        files.append(write_ply(out / "truth" / f"subscan_{k:04d}.ply", meshes, vis.ids.tolist()))
        files.append(write_csv(out / "truth" / f"subscan_{k:04d}.csv", rows, list(TRUTH_COLUMN_INFO),
                               describe=TRUTH_COLUMN_INFO, title=f"flowing foam truth at subscan {k}'s mid-time"))
        files.append(out / "truth" / f"subscan_{k:04d}.csv-metadata.json")
        ids_seen.update(vis.ids.tolist())
        counts.append(len(vis.ids))
    events = flowing_events(foam, p, seconds_per_projection)
    files.append(write_csv(out / "events.csv", events, list(EVENT_COLUMN_INFO), describe=EVENT_COLUMN_INFO,
                           title="flowing foam events"))
    files.append(out / "events.csv-metadata.json")
    shape, extent = truth_grid(c, grid_voxel)
    unit = seconds_per_projection * p
    meta = {"phantom": "flowing3d", "ndim": 3, "seed": c.seed,
            "size": [2 * c.radius, 2 * c.radius, c.z_range[1] - c.z_range[0]],
            "liquid_attenuation": c.liquid_attenuation, "bubble_contrast": c.contrast, "bubbles": len(ids_seen),
            "grid_shape": list(shape), "grid_extent": list(extent), "subscans": n_sub,
            "projections_per_subscan": p, "angles": scan.geometry.n_angles, "photons": scan.attrs.get("photons"),
            "beam": "parallel", "truth": "truth", "truth_table": "truth/subscan_{k:04d}.csv", "events": "events.csv",
            "subscan_times": [(k + 0.5) * unit for k in range(n_sub)],
            "subscan_phase": [(k + 0.5) / n_sub for k in range(n_sub)],
            "seconds_per_projection": seconds_per_projection,
            "column": {"radius_mm": c.radius, "z_range_mm": list(c.z_range), "fov_radius_mm": c.fov_radius,
                       "fov_half_height_mm": h, "rows": c.rows, "cols": c.cols, "pixel_size_mm": c.pixel_size,
                       "median_radius_mm": c.median_radius, "gap_mm": c.gap,
                       "bubbles_generated": len(c.centres), "supersampling": scan.attrs.get("supersampling"),
                       "truth_subdivisions": truth_subdivisions},
            "flowing": {"flow_px_per_subscan": round(foam.velocity / c.pixel_size, 9),
                        "vanishing": int(np.isfinite(foam.vanish_time).sum()),
                        "coalescences": [{"parents": list(map(int, m["parents"])), "child": int(m["child"]),
                                          "time_subscans": m["time"]} for m in foam.merges],
                        "gas_kept": foam.gas_kept, "bubbles_per_subscan": counts}}
    files.append(out / "phantom.json")
    atomic_write_text(out / "phantom.json", json.dumps(meta, indent=2))
    return files, meta
