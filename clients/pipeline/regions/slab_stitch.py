"""Which slab keeps which bubble: the slabs' bubbles stitched into one list, and bubbles of known identity
fitted slab by slab (the rules are in :mod:`bubsub.clients.pipeline.regions.slabs`' docstring).
"""

from __future__ import annotations

import time

import numpy as np

from bubsub.clients.pipeline.regions.slab_layout import (bubble_heights, edge_height, moved, row_axis, row_pitch,
                                                         scan_geometry, slab_bounds, slab_scan)

__all__ = ["stitch", "stitch_previews", "core_preview", "fit_known", "rows_entry", "slab_totals"]


def stitch(results, geometry):
    """One list of bubbles from the slabs' results, each bubble kept once (rules in the module docstring).

    Parameters
    ----------
    results : list of SlabResult
        In slab order.
    geometry : ScanGeometry
        The whole scan's.

    Returns
    -------
    surfaces : list of SubdivisionSurface
        Sorted by height along the rotation axis.
    summary : dict
        ``owned`` (bubbles whose centroid lies in their slab's core), ``duplicates_dropped``
        (the same bubble owned by two slabs), ``claimed_from_halo`` (a bubble no slab owned, kept
        from the one that saw it whole), ``seam_cut`` (kept bubbles reaching a slab's read edge
        inside the detector: the halo was too narrow for them).
    """
    axis = row_axis(geometry)
    pixel = row_pitch(geometry)
    rows = []  # (slab, index, centroid, radius, interior distance, owned, cut by an inner read edge)
    for res in results:
        core_lo, core_hi, read_lo, read_hi = slab_bounds(geometry, res.slab)
        for i, (c, r, z, lo, hi) in enumerate(bubble_heights(res.surfaces, geometry)):
            interior = min(lo - read_lo, read_hi - hi)
            rows.append((res.slab.index, i, c, r, interior, core_lo <= z < core_hi, interior < pixel))
    by_slab = {res.slab.index: res for res in results}
    owned = [row for row in rows if row[5]]
    # the same bubble owned by two neighbouring slabs (its centroid estimates on both sides of the seam)
    owned.sort(key=lambda row: -row[4])
    kept, dropped = [], 0
    for row in owned:
        if _same_bubble(row, kept):
            dropped += 1
            continue
        kept.append(row)
    claimed = 0
    for row in sorted((row for row in rows if not row[5] and not row[6]), key=lambda row: -row[4]):
        if not _same_bubble(row, kept):
            kept.append(row)
            claimed += 1
    kept.sort(key=lambda row: (float(row[2] @ axis), row[0], row[1]))
    surfaces = [by_slab[k].surfaces[i] for k, i, *_ in kept]
    return surfaces, {"owned": len(owned) - dropped, "duplicates_dropped": dropped, "claimed_from_halo": claimed,
                      "seam_cut": int(sum(row[6] for row in kept))}


def _same_bubble(row, kept):
    """Whether a kept bubble's centroid lies within half the smaller radius of ``row``'s."""
    if not kept:
        return False
    centres = np.array([k[2] for k in kept])
    radii = np.array([k[3] for k in kept])
    return bool(np.any(np.linalg.norm(centres - row[2], axis=1) < 0.5 * np.minimum(radii, row[3])))


def core_preview(rec, geometry, slab, origin):
    """The slices of a slab's preview (local coordinates) whose centres lie in its core, in world coordinates."""
    if rec.preview is None or rec.preview.ndim != 3:
        return None, None
    image, (x0, x1, y0, y1, z0, z1) = rec.preview, rec.preview_extent
    dz = (z1 - z0) / image.shape[0]
    z = z0 + (np.arange(image.shape[0]) + 0.5) * dz + float(origin[2])
    lo = -np.inf if slab.first else edge_height(geometry, slab, slab.core[0])
    hi = np.inf if slab.last else edge_height(geometry, slab, slab.core[1])
    keep = np.nonzero((z >= lo) & (z < hi))[0]
    if len(keep) == 0:
        return None, None
    return (np.ascontiguousarray(image[keep[0]:keep[-1] + 1], dtype=np.float32),
            (x0, x1, y0, y1, float(z[keep[0]] - 0.5 * dz), float(z[keep[-1]] + 0.5 * dz)))


def stitch_previews(results):
    """One preview from the slabs' core slices (for the overlay picture), or ``(None, None)``.

    Slabs share the preview's voxel size (it follows the field of view's radius), so their
    slices stack; the extent runs from the first part's bottom over all slices stacked.
    """
    parts = [(r.preview, r.preview_extent) for r in results if r.preview is not None]
    if not parts or len({p.shape[1:] for p, _ in parts}) != 1:
        return None, None
    image = np.concatenate([p for p, _ in parts])
    e0 = parts[0][1]
    dz = (e0[5] - e0[4]) / parts[0][0].shape[0]
    return image, (*e0[:4], e0[4], e0[4] + dz * image.shape[0])


# -- bubbles of known identity ----------------------------------------------------------------------------
def fit_known(source, surfaces, fit, plan):
    """Fit bubbles of known identity slab by slab (the warm starts of a 4D subscan; rules in the module docstring).

    Parameters
    ----------
    source : str, Path or Scan
        The scan file or the scan in memory; each slab reads its rows (:func:`slab_scan`).
    surfaces : list of SubdivisionSurface
        The bubbles' starts, world coordinates.
    fit : callable(geometry, data, surfaces) -> (list of SubdivisionSurface, dict)
        Fits surfaces to data in a slab's coordinates; the dict is its report (``iterations``,
        ``stop_reason``, ``interrupted``, ...). An error it raises ends the whole fit.
    plan : list of Slab
        :func:`plan_slabs` of the scan's rows.

    Returns
    -------
    fitted : list of SubdivisionSurface
        World coordinates, in the order of ``surfaces``, each from the slab that owns it; after an
        interrupted slab, the bubbles of the slabs not fitted are their starts.
    entries : list of dict
        Per slab (up to an interrupted one): its rows, its fit's report, ``bubbles`` (owned),
        ``bubbles_fitted`` (owned and from the halo), ``seconds_total`` (reading and fitting).
    summary : dict
        ``owned`` (bubbles kept from their slab), ``left_core`` (of them, fitted outside their slab's core:
        kept all the same), ``seam_cut`` (kept bubbles reaching their slab's read edge inside the detector:
        the halo was too narrow for them).
    """
    geometry = scan_geometry(source)
    pixel = row_pitch(geometry)
    start = [z for _, _, z, _, _ in bubble_heights(surfaces, geometry)]
    bounds = [slab_bounds(geometry, sl) for sl in plan]
    owner = [next(k for k, (lo, hi, _, _) in enumerate(bounds) if lo <= z < hi) for z in start]
    fitted, entries, summary = list(surfaces), [], {"owned": 0, "left_core": 0, "seam_cut": 0}
    for k, sl in enumerate(plan):
        t0 = time.perf_counter()
        core_lo, core_hi, read_lo, read_hi = bounds[k]
        mine = [i for i, z in enumerate(start) if read_lo <= z < read_hi]
        if mine:
            local, origin = slab_scan(source, sl)
            out, report = fit(local.geometry, local.bubble_data, [moved(surfaces[i], -origin) for i in mine])
        else:
            out, report = [], {"iterations": 0, "stop_reason": "no bubbles"}
        owned = [i for i in mine if owner[i] == k]
        for i, s in zip(mine, out):
            if owner[i] == k:
                fitted[i] = moved(s, origin)
        for _, _, z, lo, hi in bubble_heights([fitted[i] for i in owned], geometry):
            summary["left_core"] += not core_lo <= z < core_hi
            summary["seam_cut"] += min(lo - read_lo, read_hi - hi) < pixel
        summary["owned"] += len(owned)
        entries.append({**rows_entry(sl), **report, "bubbles": len(owned), "bubbles_fitted": len(mine),
                        "seconds_total": time.perf_counter() - t0})
        if report.get("interrupted"):
            break
    return fitted, entries, summary


def rows_entry(slab):
    """How a slab's entry in ``report.json`` names it."""
    return {"index": slab.index, "core_rows": list(slab.core), "read_rows": list(slab.read)}


def slab_totals(reports, keys):
    """The slabs' reports summed over ``keys``, ``interrupted`` when one was, and their stop reasons joined."""
    interrupted = any(r.get("interrupted") for r in reports)
    totals = {k: sum(r.get(k) or 0 for r in reports) for k in keys}
    totals.update(interrupted=interrupted, stop_reason="interrupted" if interrupted else
                  "; ".join(sorted({str(r.get("stop_reason")) for r in reports})))
    return totals
