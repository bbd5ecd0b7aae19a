"""Scoring a 4D reconstruction against a simulated dynamic scan: DDI per subscan and track identities."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bubsub.clients.pipeline.evaluation.scoring import json_scores, read_bubbles, score_folder, simulation_meta

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


def evaluate_dynamic(recon_dir, truth_dir, grid=None, matches=False):
    """DDI and bubble-by-bubble matching per subscan, and the fraction of (subscan, bubble) rows on the right track.

    Each ``subscan_NNNN`` folder is scored against the simulation's truth of
    that subscan as ``bubsub evaluate`` scores a reconstruct folder
    (:func:`bubsub.clients.pipeline.evaluation.scoring.score_folder`: the grid's voxels
    inside the field of view of its ``report.json``). A track's identity is
    the truth bubble its first reconstruction (the cold, latest subscan) lies
    in; a row is on the right track when the bubble lies in that same truth
    bubble at its subscan's mid-time (:func:`match_to_truth`).

    Parameters
    ----------
    recon_dir, truth_dir : str or os.PathLike
        A ``bubsub reconstruct4d`` folder and the 4D ``bubsub simulate`` folder of its scan.
    grid : ((rows, cols) or (slices, rows, cols), extent), optional
        The scoring grid; default ``phantom.json``'s.
    matches : bool
        Keep each subscan's per-bubble ``matches``, ``spurious_ids`` and report entries, and return under
        ``_images`` the label images of the subscan with the highest DDI (for
        :func:`bubsub.clients.pipeline.evaluation.evaluate.write_picture`).

    Returns
    -------
    dict
        ``subscans`` (per subscan: ``subscan``, ``ddi``, ``bubbles``, ``bubbles_truth``, ``matching``
        and, with ``matches``, the rest of :func:`score_folder`'s scores), ``mean_ddi``, ``rows``,
        ``right_track_fraction``.
    """
    recon_dir, truth_dir = Path(recon_dir), Path(truth_dir)
    meta = simulation_meta(truth_dir)
    ndim = meta["ndim"]
    if "subscans" not in meta:
        raise ValueError(f"{truth_dir} holds a static simulation; a reconstruct4d folder is scored against the 4D "
                         f"simulation of its scan")
    ext = ".ply" if ndim == 3 else ".json"
    per, tracks, worst = [], {}, None
    subs = sorted(int(p.name[8:]) for p in recon_dir.glob("subscan_*") if (p / f"bubbles{ext}").is_file())
    for k in subs:
        folder = recon_dir / f"subscan_{k:04d}"
        _, scores = score_folder(folder, truth_dir, meta, grid)
        rec, ids = read_bubbles(folder / f"bubbles{ext}", ndim)
        truth, _ = read_bubbles(truth_dir / meta["truth"] / f"subscan_{k:04d}{ext}", ndim)
        entry = {"subscan": k, "ddi": scores["ddi"], "bubbles": len(rec), "bubbles_truth": len(truth),
                 "matching": scores["matching"]}
        if matches:
            entry = {**json_scores(scores), **entry}
            if worst is None or scores["ddi"] > worst["ddi"]:
                worst = scores
        per.append(entry)
        for i, m in zip(ids, match_to_truth(rec, truth)):
            tracks.setdefault(i, []).append((k, int(m)))
    rows = right = 0
    for track in tracks.values():
        track.sort()
        identity = track[-1][1]  # the latest subscan: where the track started (backwards in time)
        rows += len(track)
        right += sum(m == identity and m >= 0 for _, m in track)
    out = {"subscans": per, "mean_ddi": float(np.mean([p["ddi"] for p in per])) if per else None,
           "rows": rows, "right_track_fraction": right / rows if rows else None}
    if matches:
        out["_images"] = None if worst is None else {**worst, "_subscans": [{"subscan": p["subscan"], "ddi": p["ddi"]}
                                                                           for p in per]}
    return out
