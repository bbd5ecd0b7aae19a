"""Bubble-by-bubble matching of two label images: which reconstructed bubble is each true bubble's, and how well.

Each truth bubble's *best* reconstructed bubble is the one covering most of
its voxels (from one overlap table of the two label images). A truth bubble
is **merged** when its best reconstructed bubble is also the best of
another truth bubble, **found** when it is not merged and their IoU
(intersection over union) is at least :data:`MIN_IOU`, and **missed**
otherwise; a reconstructed bubble that is no truth bubble's best is
**spurious**. ``bubsub evaluate`` (:mod:`bubsub.clients.pipeline.evaluation.evaluate`)
and the benchmarks (:mod:`bubsub.bench.matching`) score with it.
"""

from __future__ import annotations

import numpy as np

from bubsub.core.metrics import dice_dissimilarity

__all__ = ["overlaps", "match", "MIN_IOU"]

#: Smallest IoU of a found bubble.
MIN_IOU = 0.5


def overlaps(truth, rec):
    """Voxel counts: ``(table, n_truth, n_rec)`` with ``table[i, j] = |T_i & R_j|`` (label 0 = background)."""
    t, r = truth.ravel().astype(np.int64), rec.ravel().astype(np.int64)
    n_t, n_r = int(t.max(initial=0)) + 1, int(r.max(initial=0)) + 1
    keep = (t > 0) | (r > 0)
    counts = np.bincount(t[keep] * n_r + r[keep], minlength=n_t * n_r).reshape(n_t, n_r)
    return counts, np.bincount(t, minlength=n_t), np.bincount(r, minlength=n_r)


def match(truth, rec, cut=None, min_iou=MIN_IOU, merge_cover=None):
    """Found / missed / merged / spurious bubbles and the DDI of two label images (see the module docstring).

    Parameters
    ----------
    truth, rec : int ndarray, same shape
        Labels ``1..n`` (0 background), already restricted to the field of view.
    cut : (n_truth,) bool, optional
        Truth bubbles cut by the field of view (index ``label - 1``); their counts are given as ``cut_*``.
    min_iou : float
    merge_cover : float, optional
        Another rule for **merged**: a truth bubble is merged when one reconstructed bubble covers more than
        this fraction of its voxels and of another truth bubble's (e.g. 0.3). None: the module docstring's rule
        (a best reconstructed bubble shared by two truth bubbles).

    Returns
    -------
    dict
        ``truth`` (truth bubbles with a voxel in the field of view), ``found``, ``missed``, ``merged``,
        ``spurious``, ``reconstructed``, ``ddi``, ``median_iou`` (of the found), the same counts ``cut_*`` for the
        cut bubbles, and ``per_truth``: ``(label, best rec label or 0, IoU, status)`` rows.
    """
    table, n_t, n_r = overlaps(truth, rec)
    present = np.flatnonzero(n_t[1:] > 0) + 1
    best = np.zeros(len(n_t), dtype=np.int64)
    shared = table[:, 1:]
    has = shared.sum(axis=1) > 0
    best[has] = np.argmax(shared[has], axis=1) + 1
    owners = np.bincount(best[present], minlength=len(n_r))
    if merge_cover is None:
        merged = owners[best] > 1
        merged[best == 0] = False
    else:  # rec j covering > merge_cover of two or more truth bubbles merges all of them
        covers = table[:, 1:] > float(merge_cover) * np.maximum(n_t, 1)[:, None]
        covers[0] = False
        merged = (covers & (covers.sum(axis=0) > 1)[None, :]).any(axis=1)
    rows = []
    for i in present:
        j = int(best[i])
        iou = 0.0 if j == 0 else table[i, j] / (n_t[i] + n_r[j] - table[i, j])
        status = "merged" if merged[i] else ("found" if iou >= min_iou else "missed")
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
