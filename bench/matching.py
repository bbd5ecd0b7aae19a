"""Bubble-by-bubble scores of a reconstruction of a simulated column, inside the field of view.

Both label images live on the simulation folder's evaluation grid
(``phantom.json``'s ``grid_shape`` / ``grid_extent``: the detector's rows
over the liquid cylinder), with the voxels outside the field of view set to
0. The truth is rasterised from the analytic ellipsoids of ``truth.csv``.

Found, missed, merged and spurious bubbles are :func:`bubsub.core.matching.match`'s (a truth bubble's
best reconstructed bubble covers most of its voxels; found at IoU >= 0.5), here inside the field of view.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from bubsub.core.matching import MIN_IOU, match, overlaps
from bubsub.clients.pipeline.inputs.fov import fov_mask
from bubsub.core.foam.ellipsoids import ellipsoid_labels
from bubsub.core.metrics import label_image

__all__ = ["column_truth", "truth_labels", "mesh_labels", "overlaps", "match", "MIN_IOU"]


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
    c = meta["column"]
    return fov_mask(tuple(meta["grid_shape"]), tuple(meta["grid_extent"]), (c["fov_radius_mm"], c["fov_half_height_mm"]))


def truth_labels(meta, table):
    """Label image of the truth (``truth.csv`` id + 1) on the evaluation grid, 0 outside the field of view."""
    centres = np.stack([table[f"centre_{a}_mm"] for a in "xyz"], axis=1)
    axes = np.stack([table[f"semi_axis_{k}_mm"] for k in (1, 2, 3)], axis=1)
    rot = np.stack([table[f"rotation_{i}{j}"] for i in (1, 2, 3) for j in (1, 2, 3)], axis=1).reshape(-1, 3, 3)
    labels = ellipsoid_labels(centres, axes, rot, tuple(meta["grid_shape"]), tuple(meta["grid_extent"]))
    labels[~_fov_mask(meta)] = 0
    return labels


def mesh_labels(meshes, meta):
    """Label image of meshes (index + 1) on the evaluation grid, 0 outside the field of view."""
    labels = label_image(meshes, tuple(meta["grid_shape"]), tuple(meta["grid_extent"]))
    labels[~_fov_mask(meta)] = 0
    return labels
