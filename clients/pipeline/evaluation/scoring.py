"""Scores of reconstructed bubbles against simulated ones: DDI, bubble-by-bubble matches, size errors.

:func:`score_bubbles` rasterises both sets on the simulation's grid
(``phantom.json``'s ``grid_shape`` / ``grid_extent``), counting only its
voxels inside the field of view, and gives the DDI, the matching of
:func:`bubsub.core.matching.match` and each match's size errors;
:func:`score_folder` does so for a ``bubsub reconstruct`` folder (or a
``subscan_NNNN`` folder of ``bubsub reconstruct4d``) against the truth of its
simulation. ``bubsub evaluate`` (:mod:`.evaluate`) and the 4D evaluation
(:mod:`.evaluate4d`) score with them.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from bubsub.clients.pipeline.inputs.fov import fov_mask
from bubsub.core.io.meshio import read_ply, read_polygons_json
from bubsub.core.matching import MIN_IOU, match
from bubsub.core.metrics import label_image

__all__ = ["score_bubbles", "score_folder", "read_bubbles", "simulation_meta", "scored_field_of_view",
           "json_scores"]

_SUBSCAN = re.compile(r"subscan_(\d+)$")
#: Report entries copied into the evaluation: what the reconstruction says of itself.
_REPORT_KEYS = ("final_objective", "iterations", "stop_reason", "delivered_fit", "holdout_mse",
                "holdout_mse_voxel_bb", "seconds_total")


def read_bubbles(path, ndim):
    """``(items, ids)``: the bubbles of a ``.json`` (2D polygons) or ``.ply`` (3D meshes) file and their ids."""
    items, ids = (read_ply if ndim == 3 else read_polygons_json)(path, with_ids=True)
    return list(items), [int(i) for i in ids]


def simulation_meta(truth_dir):
    """``phantom.json`` of a simulation folder, or a ValueError saying how to make one."""
    meta_path = Path(truth_dir) / "phantom.json"
    if not meta_path.is_file():
        raise ValueError(f"{truth_dir} is not a simulation folder (no phantom.json); make one with bubsub simulate")
    return json.loads(meta_path.read_text())


def score_folder(recon_dir, truth_dir, meta, grid=None):
    """``(kind, scores)`` of one reconstruct folder (or ``subscan_NNNN`` folder) against its truth.

    ``kind`` is ``static`` or ``subscan``; ``scores`` is :func:`score_bubbles`'s (label images included),
    with ``subscan`` and the report's ``reconstruction`` entries. ``grid``: ``(shape, extent)`` of the
    scoring; default ``phantom.json``'s (``meta``).
    """
    ndim = meta["ndim"]
    ext = ".ply" if ndim == 3 else ".json"
    report_path = recon_dir / "report.json"
    report = json.loads(report_path.read_text()) if report_path.is_file() else {}
    if report.get("dimension", ndim) != ndim:
        raise ValueError(f"{report_path} describes a {report['dimension']}D reconstruction but the truth in "
                         f"{truth_dir} is {ndim}D")
    kind, subscan = "static", None
    if "subscans" in meta:
        m = _SUBSCAN.search(recon_dir.resolve().name)
        if m is None:
            raise ValueError(f"{truth_dir} is a 4D simulation (one truth per subscan) but {recon_dir} is no "
                             f"subscan_NNNN folder; score the bubsub reconstruct4d folder or one of its subscans")
        kind, subscan = "subscan", int(m.group(1))
        truth_path = truth_dir / meta["truth"] / f"subscan_{subscan:04d}{ext}"
        if not truth_path.is_file():
            raise ValueError(f"{truth_dir} has no truth for subscan {subscan} ({truth_path.name}); it simulates "
                             f"{meta['subscans']} subscans")
    else:
        truth_path = truth_dir / meta["truth"]
    rec, rec_ids = read_bubbles(recon_dir / f"bubbles{ext}", ndim)
    truth, truth_ids = read_bubbles(truth_path, ndim)
    shape, extent = grid if grid is not None else (tuple(meta["grid_shape"]), tuple(meta["grid_extent"]))
    scores = score_bubbles(rec, rec_ids, truth, truth_ids, shape, extent, scored_field_of_view(report, meta))
    if subscan is not None:
        scores = {"subscan": subscan, **scores}
    scores["reconstruction"] = {k: report[k] for k in _REPORT_KEYS if k in report}
    return kind, scores


def scored_field_of_view(report, meta):
    """``(radius, half_height)`` mm of the scan: the reconstruction report's, else a column simulation's; or None."""
    f = report.get("field_of_view_mm")
    if f is not None:
        return float(f["radius"]), float(f["half_height"])
    c = meta.get("column")
    if c is not None and "fov_radius_mm" in c:
        return float(c["fov_radius_mm"]), float(c["fov_half_height_mm"])
    return None


def score_bubbles(rec, rec_ids, truth, truth_ids, shape, extent, fov=None):
    """DDI, bubble-by-bubble matches and size errors of reconstructed bubbles against true ones on one grid.

    Parameters
    ----------
    rec, truth : list of Polygon (2D) or Mesh (3D)
    rec_ids, truth_ids : list of int
        Their ids (as in their files).
    shape : (rows, cols) or (slices, rows, cols)
    extent : (xmin, xmax, ymin, ymax[, zmin, zmax])
        mm; the grid convention of :mod:`bubsub.core.projection.masks`.
    fov : (radius, half_height), optional
        mm; only the grid's voxels inside it count (:func:`bubsub.clients.pipeline.inputs.fov.fov_mask`).

    Returns
    -------
    dict
        As :func:`evaluate_dir`'s static entries, plus ``_truth_labels``, ``_rec_labels`` (int32,
        ``shape``; 0 outside the field of view) and ``_extent`` for the picture (not JSON: dropped by
        :func:`json_scores`).
    """

    ndim = len(shape)
    t_lab, r_lab = label_image(truth, shape, extent), label_image(rec, shape, extent)
    keep = np.ones(shape, dtype=bool) if fov is None else fov_mask(shape, extent, fov)
    t_lab[~keep], r_lab[~keep] = 0, 0
    m = match(t_lab, r_lab, min_iou=MIN_IOU)
    counts_t = np.bincount(t_lab.ravel(), minlength=len(truth) + 1)
    counts_r = np.bincount(r_lab.ravel(), minlength=len(rec) + 1)
    sides = np.array([extent[2 * k + 1] - extent[2 * k] for k in range(ndim)]) / np.array(shape[::-1])
    cell = float(np.prod(sides))  # mm^2 or mm^3 per voxel
    size_key = "area_mm2" if ndim == 2 else "volume_mm3"

    def diameter(size):
        return 2.0 * np.sqrt(size / np.pi) if ndim == 2 else np.cbrt(6.0 * size / np.pi)

    matches = []
    for label, best, iou, status in m["per_truth"]:
        t_size = counts_t[label] * cell
        entry = {"truth_id": truth_ids[label - 1], "reconstructed_id": rec_ids[best - 1] if best else None,
                 "status": status, "iou": iou, f"truth_{size_key}": t_size,
                 "truth_equivalent_diameter_mm": float(diameter(t_size))}
        if best:
            r_size = counts_r[best] * cell
            entry.update({f"reconstructed_{size_key}": r_size,
                          "reconstructed_equivalent_diameter_mm": float(diameter(r_size)),
                          f"{size_key[:-4]}_error_{size_key[-3:]}": r_size - t_size,
                          "equivalent_diameter_error_mm": float(diameter(r_size) - diameter(t_size)),
                          "centroid_distance_mm": float(np.linalg.norm(
                              np.asarray(rec[best - 1].centroid) - np.asarray(truth[label - 1].centroid)))})
        matches.append(entry)
    owners = {e["reconstructed_id"] for e in matches}
    spurious = [i for k, i in enumerate(rec_ids) if counts_r[k + 1] > 0 and i not in owners]
    errors = np.array([e["equivalent_diameter_error_mm"] for e in matches if e["status"] == "found"])
    matching = {"rule": f"a true bubble's best reconstructed bubble covers most of its voxels; found: IoU >= "
                        f"{MIN_IOU} and not shared with another true bubble (merged), else missed",
                "found": m["found"], "missed": m["missed"], "merged": m["merged"], "spurious": len(spurious),
                "median_iou": None if not m["found"] else m["median_iou"],
                "mean_equivalent_diameter_error_mm": float(errors.mean()) if errors.size else None,
                "median_abs_equivalent_diameter_error_mm": float(np.median(np.abs(errors))) if errors.size else None}
    where = "the whole truth grid" if fov is None else "the truth grid's voxels inside the field of view"
    return {
        "ddi": m["ddi"], "scored_on": where,
        "field_of_view": None if fov is None else {"radius_mm": fov[0],
                                                   "half_height_mm": fov[1] if ndim == 3 else None},
        "voxels_scored": int(keep.sum()), "voxels": int(keep.size), "voxel_size_mm": [float(s) for s in sides],
        "grid_shape": [int(n) for n in shape], "grid_extent_mm": [float(e) for e in extent],
        "bubbles_reconstructed": len(rec), "bubbles_truth": len(truth),
        "matching": matching, "matches": matches, "spurious_ids": spurious,
        "_truth_labels": t_lab, "_rec_labels": r_lab, "_extent": tuple(extent),
    }


def json_scores(scores):
    """:func:`score_bubbles`'s (or :func:`score_folder`'s) scores without the label images: the JSON-able part."""
    return {k: v for k, v in scores.items() if not k.startswith("_")}
