"""Scoring a reconstruction folder against a simulation folder (DDI, held-out MSE)."""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["evaluate_dir"]


def evaluate_dir(recon_dir, truth_dir):
    """DDI of a reconstruction against the simulated ground truth (and held-out MSE if any).

    The DDI counts the truth grid's voxels inside the field of view only
    (the part of the sample the data see; a bubble's part beyond the
    detector's top row is neither measured nor scored): the field of view of
    the reconstruction's ``report.json`` (``field_of_view_mm``), else that of
    a column simulation's ``phantom.json``; the whole grid when neither
    gives one.

    Returns
    -------
    dict
        ``ddi``, ``scored_on``, ``field_of_view_mm`` and ``voxels_in_fov``
        (when a field of view is known), ``grid_shape``, bubble counts and
        the report's held-out MSE, objective, seconds and stop reason.
    """
    from bubsub.core.io.meshio import read_ply, read_polygons_json
    from bubsub.core.metrics import bubble_mask, dice_dissimilarity, shapes_dice_dissimilarity
    from bubsub.clients.pipeline.fov import fov_mask

    recon_dir, truth_dir = Path(recon_dir), Path(truth_dir)
    meta_path = truth_dir / "phantom.json"
    if not meta_path.is_file():
        raise ValueError(f"{truth_dir} is not a simulation folder (no phantom.json); make one with bubsub simulate")
    meta = json.loads(meta_path.read_text())
    ndim = meta["ndim"]
    name = "bubbles.ply" if ndim == 3 else "bubbles.json"
    if not (recon_dir / name).is_file():
        raise ValueError(f"{recon_dir} holds no {name} (a {ndim}D result, like the truth); run bubsub reconstruct "
                         f"on the {ndim}D scan first")
    report = recon_dir / "report.json"
    r = json.loads(report.read_text()) if report.is_file() else {}
    if r.get("dimension", ndim) != ndim:
        raise ValueError(f"{report} describes a {r['dimension']}D reconstruction but the truth in {truth_dir} "
                         f"is {ndim}D")
    reader = read_ply if ndim == 3 else read_polygons_json
    rec = reader(recon_dir / name)
    truth = reader(truth_dir / meta["truth"])
    shape, extent = tuple(meta["grid_shape"]), tuple(meta["grid_extent"])
    fov = _field_of_view(r, meta)
    if fov is None:  # nothing says what the data saw: the whole grid
        out = {"ddi": shapes_dice_dissimilarity(rec, truth, shape, extent), "scored_on": "the whole truth grid"}
    else:
        keep = fov_mask(shape, extent, fov)
        out = {"ddi": dice_dissimilarity(bubble_mask(rec, shape, extent)[keep], bubble_mask(truth, shape, extent)[keep]),
               "scored_on": "the truth grid's voxels inside the field of view",
               "field_of_view_mm": {"radius": fov[0], "half_height": fov[1]},
               "voxels_in_fov": f"{int(keep.sum())} of {keep.size}"}
    out.update({"grid_shape": list(shape), "bubbles_reconstructed": len(rec), "bubbles_truth": len(truth)})
    for k in ("holdout_mse", "holdout_mse_voxel_bb", "final_objective", "seconds_total", "iterations", "stop_reason"):
        if k in r:
            out[k] = r[k]
    return out


def _field_of_view(report, meta):
    """``(radius, half_height)`` mm of the scan: the reconstruction report's, else a column simulation's; or None."""
    f = report.get("field_of_view_mm")
    if f is not None:
        return float(f["radius"]), float(f["half_height"])
    c = meta.get("column")
    if c is not None and "fov_radius_mm" in c:
        return float(c["fov_radius_mm"]), float(c["fov_half_height_mm"])
    return None
