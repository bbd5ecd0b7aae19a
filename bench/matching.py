"""Bubble-by-bubble scores of a reconstruction of a simulated column, inside the field of view.

Both label images live on the simulation folder's evaluation grid
(``phantom.json``'s ``grid_shape`` / ``grid_extent``: the detector's rows
over the liquid cylinder), with the voxels outside the field of view set to
0. The truth is rasterised from the analytic ellipsoids of ``truth.csv``.

Each truth bubble's *best* reconstructed bubble is the one covering most of
its voxels (as in :func:`bubsub.bench.bubbles.per_bubble`, here from one
overlap table instead of one pass over the grid per bubble). A truth bubble
is **merged** when its best reconstructed bubble is also the best of
another truth bubble, **found** when it is not merged and their IoU
(intersection over union inside the field of view) is at least 0.5, and
**missed** otherwise; a reconstructed bubble inside the field of view that
is no truth bubble's best is **spurious**.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

__all__ = ["column_truth", "truth_labels", "mesh_labels", "overlaps", "match", "MIN_IOU"]

#: Smallest IoU of a found bubble.
MIN_IOU = 0.5


def column_truth(sim_dir):
    """``(meta, table)`` of a column's simulation folder: ``phantom.json`` and ``truth.csv`` as float arrays."""
    sim_dir = Path(sim_dir)
    meta = json.loads((sim_dir / "phantom.json").read_text())
    if meta.get("phantom") != "column":
        raise ValueError(f"{sim_dir} is not a column simulation (make one with bubsub simulate --phantom column)")
    with open(sim_dir / meta["truth_table"], newline="") as fh:
        rows = list(csv.DictReader(fh))
    table = {k: np.array([float(r[k]) for r in rows]) for k in (rows[0] if rows else {})}
    return meta, table


def _fov_mask(meta):
    from bubsub.clients.pipeline.fov import fov_mask

    c = meta["column"]
    return fov_mask(tuple(meta["grid_shape"]), tuple(meta["grid_extent"]), (c["fov_radius_mm"], c["fov_half_height_mm"]))


def truth_labels(meta, table):
    """Label image of the truth (``truth.csv`` id + 1) on the evaluation grid, 0 outside the field of view."""
    from bubsub.core.foam.ellipsoids import ellipsoid_labels

    centres = np.stack([table[f"centre_{a}_mm"] for a in "xyz"], axis=1)
    axes = np.stack([table[f"semi_axis_{k}_mm"] for k in (1, 2, 3)], axis=1)
    rot = np.stack([table[f"rotation_{i}{j}"] for i in (1, 2, 3) for j in (1, 2, 3)], axis=1).reshape(-1, 3, 3)
    labels = ellipsoid_labels(centres, axes, rot, tuple(meta["grid_shape"]), tuple(meta["grid_extent"]))
    labels[~_fov_mask(meta)] = 0
    return labels


def mesh_labels(meshes, meta):
    """Label image of meshes (index + 1) on the evaluation grid, 0 outside the field of view."""
    from bubsub.core.metrics import label_image

    labels = label_image(meshes, tuple(meta["grid_shape"]), tuple(meta["grid_extent"]))
    labels[~_fov_mask(meta)] = 0
    return labels


def overlaps(truth, rec):
    """Voxel counts: ``(table, n_truth, n_rec)`` with ``table[i, j] = |T_i & R_j|`` (label 0 = background)."""
    t, r = truth.ravel().astype(np.int64), rec.ravel().astype(np.int64)
    n_t, n_r = int(t.max(initial=0)) + 1, int(r.max(initial=0)) + 1
    keep = (t > 0) | (r > 0)
    counts = np.bincount(t[keep] * n_r + r[keep], minlength=n_t * n_r).reshape(n_t, n_r)
    return counts, np.bincount(t, minlength=n_t), np.bincount(r, minlength=n_r)


def match(truth, rec, cut=None, min_iou=MIN_IOU):
    """Found / missed / merged / spurious bubbles and the DDI of two label images (see the module docstring).

    Parameters
    ----------
    truth, rec : int ndarray, same shape
        Labels ``1..n`` (0 background), already restricted to the field of view.
    cut : (n_truth,) bool, optional
        Truth bubbles cut by the field of view (index ``label - 1``); their counts are given as ``cut_*``.
    min_iou : float

    Returns
    -------
    dict
        ``truth`` (truth bubbles with a voxel in the field of view), ``found``, ``missed``, ``merged``,
        ``spurious``, ``reconstructed``, ``ddi``, ``median_iou`` (of the found), the same counts ``cut_*`` for the
        cut bubbles, and ``per_truth``: ``(label, best rec label or 0, IoU, status)`` rows.
    """
    from bubsub.core.metrics import dice_dissimilarity

    table, n_t, n_r = overlaps(truth, rec)
    present = np.flatnonzero(n_t[1:] > 0) + 1
    best = np.zeros(len(n_t), dtype=np.int64)
    shared = table[:, 1:]
    has = shared.sum(axis=1) > 0
    best[has] = np.argmax(shared[has], axis=1) + 1
    owners = np.bincount(best[present], minlength=len(n_r))
    rows = []
    for i in present:
        j = int(best[i])
        iou = 0.0 if j == 0 else table[i, j] / (n_t[i] + n_r[j] - table[i, j])
        status = "merged" if j and owners[j] > 1 else ("found" if iou >= min_iou else "missed")
        rows.append((int(i), j, float(iou), status))
    recs = np.flatnonzero(n_r[1:] > 0) + 1
    out = {"truth": len(present), "reconstructed": len(recs),
           "spurious": int(np.sum(owners[recs] == 0)),
           "ddi": float(dice_dissimilarity(rec > 0, truth > 0)),
           "median_iou": float(np.median([r[2] for r in rows if r[3] == "found"] or [np.nan])),
           "per_truth": rows}
    for s in ("found", "missed", "merged"):
        out[s] = sum(1 for r in rows if r[3] == s)
    if cut is not None:
        cut = np.asarray(cut, dtype=bool)
        chosen = [r for r in rows if cut[r[0] - 1]]
        out["cut_truth"] = len(chosen)
        for s in ("found", "missed", "merged"):
            out[f"cut_{s}"] = sum(1 for r in chosen if r[3] == s)
    return out
