"""Scoring a 4D reconstruction against a simulated dynamic scan: DDI per subscan and track identities."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["evaluate_dynamic", "match_to_truth"]


def match_to_truth(items, truth):
    """Index of the truth bubble nearest to each item's centroid, or -1 if the centroid lies outside it.

    Parameters
    ----------
    items, truth : sequence of Polygon / Mesh

    Returns
    -------
    (n_items,) int
    """
    if not items:
        return np.zeros(0, int)
    tc = np.array([t.centroid for t in truth])
    tr = np.array([t.equivalent_radius for t in truth])
    out = []
    for it in items:
        d = np.linalg.norm(tc - np.asarray(it.centroid), axis=1)
        k = int(np.argmin(d))
        out.append(k if d[k] < tr[k] else -1)
    return np.array(out)


def _read(path, ndim):
    from bubsub.core.io.meshio import read_ply, read_polygons_json

    return (read_ply if ndim == 3 else read_polygons_json)(path, with_ids=True)


def evaluate_dynamic(recon_dir, truth_dir, grid=None):
    """DDI per subscan and the fraction of (subscan, bubble) rows on the right track.

    A track's identity is the truth bubble its first reconstruction (the
    cold, latest subscan) lies in; a row is on the right track when the
    bubble lies in that same truth bubble at its subscan's mid-time.
    ``grid``: ``(shape, extent)`` of the DDI; default that of ``phantom.json``.

    Returns
    -------
    dict
        ``subscans`` (per subscan: ``subscan``, ``ddi``, ``bubbles``,
        ``bubbles_truth``), ``mean_ddi``, ``rows``, ``right_track_fraction``.
    """
    from bubsub.core.metrics import shapes_dice_dissimilarity

    recon_dir, truth_dir = Path(recon_dir), Path(truth_dir)
    meta = json.loads((truth_dir / "phantom.json").read_text())
    ndim = meta["ndim"]
    shape, extent = grid if grid is not None else (tuple(meta["grid_shape"]), tuple(meta["grid_extent"]))
    ext = ".ply" if ndim == 3 else ".json"
    per, matches = [], {}
    subs = sorted(int(p.name[8:]) for p in recon_dir.glob("subscan_*") if (p / "report.json").is_file())
    for k in subs:
        rec, ids = _read(recon_dir / f"subscan_{k:04d}" / f"bubbles{ext}", ndim)
        truth, _ = _read(truth_dir / meta["truth"] / f"subscan_{k:04d}{ext}", ndim)
        per.append({"subscan": k, "ddi": shapes_dice_dissimilarity(rec, truth, shape, extent),
                    "bubbles": len(rec), "bubbles_truth": len(truth)})
        for i, m in zip(ids, match_to_truth(rec, truth)):
            matches.setdefault(i, []).append((k, int(m)))
    rows = right = 0
    for track in matches.values():
        track.sort()
        identity = track[-1][1]  # the latest subscan: where the track started (backwards in time)
        rows += len(track)
        right += sum(m == identity and m >= 0 for _, m in track)
    return {"subscans": per, "mean_ddi": float(np.mean([p["ddi"] for p in per])) if per else None,
            "rows": rows, "right_track_fraction": right / rows if rows else None}
