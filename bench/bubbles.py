"""Benchmark "bubbles": where BubSub's error comes from on one simulated scan, bubble by bubble.

``python -m bubsub.bench bubbles EXPERIMENT [--quick] [--angles N] [--seed S] [--set NAME=VALUE ...]``

Simulates the scan of one case of an experiment (``fig1a``, ``dense2d``,
``dense3d``, ...; the same phantom, noise and evaluation grid as
``bubsub experiment``), counts the initial centres each detector finds in
the voxel preview against the truth, reconstructs with
:class:`~bubsub.clients.pipeline.reconstruct.ReconstructionSettings`
(``--set`` overrides fields, e.g. ``--set detector=dt --set separation=1``),
and prints, per truth bubble, the reconstructed bubble covering most of it,
their Dice dissimilarity, and whether that bubble also covers most of
another truth bubble (merged). The totals say whether the error is in
missed, merged or spurious bubbles or along the boundaries (false positives
within two voxels of the gas).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np
from scipy import ndimage

from bubsub.clients.experiments.runner import EXPERIMENTS, case_config, simulate_case
from bubsub.clients.pipeline.static.initial import initial_centres
from bubsub.clients.pipeline.static.preview import voxel_preview
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, reconstruct
from bubsub.core.metrics import dice_dissimilarity
from bubsub.core.voxel.grid import world_to_index
from bubsub.core.projection.masks import label_image

__all__ = ["main", "count_centres", "per_bubble", "setting_value"]


def count_centres(labels, centres, extent):
    """``(one, missed, multi, spurious)``: truth bubbles holding exactly one, no, several centres; centres in liquid."""
    idx = np.round(world_to_index(np.asarray(centres).reshape(-1, labels.ndim), labels.shape, extent)).astype(int)
    idx = np.clip(idx, 0, np.array(labels.shape) - 1)
    counts = np.bincount(labels[tuple(idx.T)], minlength=int(labels.max()) + 1)
    return int(np.sum(counts[1:] == 1)), int(np.sum(counts[1:] == 0)), int(np.sum(counts[1:] > 1)), int(counts[0])


def per_bubble(truth_labels, rec_labels):
    """One row per truth bubble: ``(truth id, voxels, reconstructed id or 0, DDI, merged with [truth ids])``."""
    rows, owner = [], {}
    for i in range(1, int(truth_labels.max()) + 1):
        t = truth_labels == i
        ids, counts = np.unique(rec_labels[t], return_counts=True)
        counts, ids = counts[ids > 0], ids[ids > 0]
        if len(ids) == 0:
            rows.append([i, int(t.sum()), 0, 1.0])
            continue
        j = int(ids[np.argmax(counts)])
        owner.setdefault(j, []).append(i)
        rows.append([i, int(t.sum()), j, float(dice_dissimilarity(rec_labels == j, t))])
    return [(*r, owner[r[2]] if r[2] and len(owner[r[2]]) > 1 else []) for r in rows], owner


def setting_value(text, current):
    """``--set NAME=VALUE``'s text as a settings field whose value is ``current``: of its type (bool from
    1/true/yes; an unset field's as int when it reads as one, else the text)."""
    if isinstance(current, bool):
        return text.lower() in ("1", "true", "yes")
    if current is None:
        try:
            return int(text)
        except ValueError:
            return text
    return type(current)(text)


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m bubsub.bench bubbles", description=__doc__.split("\n\n")[0])
    p.add_argument("experiment", choices=sorted(EXPERIMENTS))
    p.add_argument("--quick", action="store_true")
    p.add_argument("--angles", type=int, default=25)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--photons", type=float, default=1e4)
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="a ReconstructionSettings field, e.g. detector=dt, separation=1, control_points=162")
    a = p.parse_args(argv)
    exp = EXPERIMENTS[a.experiment]
    cfg = case_config(exp, a.quick)
    ph, scan, shape, extent = simulate_case(exp.ndim, a.seed, a.angles, a.photons, cfg, a.quick, exp.phantom == "dense")
    truth_labels = label_image(ph.bubbles, shape, extent)
    truth = truth_labels > 0
    print(f"{a.experiment}{' (quick)' if a.quick else ''}, {a.angles} views, seed {a.seed}: "
          f"{len(ph.bubbles)} bubbles, gas fraction {truth.mean():.2f}, grid {shape}")
    image, ext = voxel_preview(scan.bubble_data, scan.geometry, scan.bubble_contrast, method="box")
    for det in ("dt", "log"):
        centres, _ = initial_centres(image, ext, detector=det, contrast=scan.bubble_contrast)
        one, missed, multi, spurious = count_centres(truth_labels, centres, extent)
        print(f"preview centres ({det}): {len(centres)}; truth bubbles with one {one}, none {missed}, "
              f"several {multi}; centres in liquid {spurious}")
    s = ReconstructionSettings(iterations=cfg["iterations"], progress=False)
    fields = {f.name for f in dataclasses.fields(s)}
    for item in a.set:
        name, _, text = item.partition("=")
        if name not in fields:
            p.error(f"--set {item}: ReconstructionSettings has no field {name!r}")
        s = dataclasses.replace(s, **{name: setting_value(text, getattr(s, name))})
    cpu, wall = time.process_time(), time.perf_counter()
    rec = reconstruct(scan, s)
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    rec_labels = label_image([x.fine() for x in rec.surfaces], shape, extent)
    mask = rec_labels > 0
    rows, owner = per_bubble(truth_labels, rec_labels)
    init = rec.report.get("initialisation") or {}
    print(f"BubSub: {len(rec.surfaces)} bubbles, DDI {dice_dissimilarity(mask, truth):.4f}, "
          f"detector {init.get('detector')}, {cpu:.0f} s CPU, {wall:.0f} s wall")
    ref = rec.report.get("refinement")
    if ref:
        print(f"refinement {ref['control_vertices_before']} -> {ref['control_vertices_after']} control vertices: "
              f"{'kept' if ref['kept'] else 'not kept'} (Akaike score {ref['score_before']:.1f} -> "
              f"{ref['score_after']:.1f}, after repair {ref.get('score_after_repair', float('nan')):.1f}; "
              f"{ref['iterations']} iterations)")
    changes = [c["change"] for c in (rec.report["topology"] or {}).get("changes", [])]
    print(f"topology changes: {', '.join(changes) or 'none'}; validity actions: "
          f"{', '.join(x['action'] for x in rec.report['validity']['actions']) or 'none'}")

    near = ndimage.distance_transform_edt(~truth) <= 2
    fp, fn = mask & ~truth, ~mask & truth
    print(f"false positives {int(fp.sum())} ({int((fp & near).sum())} within 2 voxels of gas), "
          f"false negatives {int(fn.sum())}, of {int(truth.sum())} gas voxels")
    print(f"{'truth':>5} {'voxels':>8} {'rec':>4} {'DDI':>6}  merged with")
    for i, n, j, d, merged in rows:
        print(f"{i:5d} {n:8d} {j:4d} {d:6.3f}  {merged if merged else ('MISSED' if j == 0 else '')}")
    spurious = [j for j in range(1, len(rec.surfaces) + 1) if j not in owner]
    merged = sum(1 for r in rows if r[4])
    print(f"merged truth bubbles {merged}, missed {sum(1 for r in rows if r[2] == 0)}, "
          f"spurious reconstructed bubbles {len(spurious)}")
    return 0
