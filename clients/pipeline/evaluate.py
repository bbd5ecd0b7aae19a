"""Scoring a reconstruction folder against a simulation folder (DDI, held-out MSE)."""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["evaluate_dir"]


def evaluate_dir(recon_dir, truth_dir):
    """DDI of a reconstruction against the simulated ground truth (and held-out MSE if any)."""
    from bubsub.core.io.meshio import read_ply, read_polygons_json
    from bubsub.core.metrics import shapes_dice_dissimilarity

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
    out = {"ddi": shapes_dice_dissimilarity(rec, truth, shape, extent), "grid_shape": list(shape),
           "bubbles_reconstructed": len(rec), "bubbles_truth": len(truth)}
    for k in ("holdout_mse", "holdout_mse_voxel_bb", "final_objective", "seconds_total", "iterations", "stop_reason"):
        if k in r:
            out[k] = r[k]
    return out
