"""``bubsub bench detection``: small bubbles and edge caps, seeded and found, against the voxel route.

A foam column (:func:`bubsub.core.foam.column.column_phantom`: polydisperse
rotated ellipsoids in a liquid cylinder, parallel beam, exact chords with
2 x 2 sub-rays, Poisson noise at I0 = 1e4) on a small detector (default
40 projections of 128 x 384 pixels of 12 um, about 150 bubbles in view),
where a share of the bubbles (``--small-share``, 0.3) is shrunk in place to
equivalent radii drawn uniformly from ``--small-range`` pixels (5-13): the
small bubbles that coarsening leaves between the others. Bubbles cut by the
top and bottom rows follow from the column's height. ``--phantom flowing``
takes one subscan (``--subscan``) of the flowing foam instead
(:func:`flowing_subscan`: ``bubsub simulate --phantom flowing3d``'s
defaults, the foam moving, shrinking and growing during the subscan, the
truth at its mid-time).

Each truth bubble is put in a class by the radius of the ball of its
visible part's volume (the part between the detector's top and bottom
planes, exact):

* ``small``: wholly in view, that ball 6 to 12 pixels in radius;
* ``cap``: cut by the top or bottom row, that ball 6 to 12 pixels in radius;
* ``tiny``: that ball under 6 pixels (not a target; counted apart);
* ``large``: the rest.

Per class it counts the truth bubbles **seeded** (a centre of the pipeline's
initial bubbles, :func:`bubsub.clients.pipeline.reconstruct.initial_bubbles`
on the data, lies inside the truth ellipsoid) and **found** after ``bubsub
reconstruct`` (in-process, its defaults; options of ``--set NAME=VALUE``),
and after the voxel route on the same scan (SIRT ``--sirt-iterations`` +
Otsu + distance watershed, :func:`bubsub.bench.fov.voxel_route`), scored
inside the field of view on the evaluation grid (:mod:`bubsub.bench.matching`:
found when IoU >= 0.5 and not merged). Also the totals (found, missed,
merged, spurious, DDI) and the seconds.

``python -m bubsub.bench detection [--bubbles 150] [--seed 0] [--phantom small|flowing] [--subscan K] [--data DIR]
[--no-voxel] [--seeds-only] [--set NAME=VALUE ...]`` (docs/scale.md)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from bubsub.bench.bubbles import setting_value
from bubsub.bench.fov import voxel_route
from bubsub.bench.matching import column_truth, match, mesh_labels, truth_labels
from bubsub.bench.scale import table
from bubsub.clients.pipeline.inputs.fov import fov_mask
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, initial_bubbles, reconstruct
from bubsub.core import MeshProjector
from bubsub.core.foam.column import TRUTH_COLUMN_INFO, column_phantom, simulate_column, truth_grid, write_column
from bubsub.core.foam.ellipsoids import shape_matrices
from bubsub.core.foam.flowing import FLOWING_DEFAULTS, flowing_foam
from bubsub.core.foam.flowing_scan import simulate_flowing, truth_rows
from bubsub.core.io.scanfile import Scan, read_scan, write_scan
from bubsub.core.io.tables import write_csv

__all__ = ["small_column", "flowing_subscan", "size_classes", "seeded", "CLASSES", "main"]

#: The classes of truth bubbles, in the tables' order.
CLASSES = ("small", "cap", "tiny", "large")

#: The target range of the radius of the ball of a visible part's volume, pixels.
TARGET_BALL = (6.0, 12.0)


def small_column(n_bubbles=150, *, seed=0, rows=128, cols=384, small_share=0.3, small_range=(5.0, 13.0)):
    """A column phantom with a share of its bubbles shrunk in place to small equivalent radii.

    Parameters
    ----------
    n_bubbles : int
        About this many bubbles in the detector's rows before shrinking (:func:`column_phantom`).
    seed : int
        Of the column and of the choice and sizes of the shrunk bubbles.
    rows, cols : int
        Detector, pixels of 12 um.
    small_share : float
        Share of all bubbles shrunk, in [0, 1].
    small_range : (float, float)
        Equivalent radii of the shrunk bubbles are uniform in this range, pixels.

    Returns
    -------
    ColumnPhantom
        Its bubbles keep their centres and orientations; shrinking keeps them disjoint.
    """
    if not 0 <= small_share <= 1:
        raise ValueError(f"small_share must be in [0, 1], got {small_share}")
    lo, hi = map(float, small_range)
    if not 0 < lo <= hi:
        raise ValueError(f"small_range must be 0 < low <= high pixels, got {small_range}")
    p = column_phantom(n_bubbles, seed=seed, rows=rows, cols=cols)
    rng = np.random.default_rng([seed, 41])
    n = len(p.axes)
    pick = rng.choice(n, size=int(round(small_share * n)), replace=False)
    r_eq = np.cbrt(np.prod(p.axes, axis=1))
    target = rng.uniform(lo, hi, size=len(pick)) * p.pixel_size
    axes = np.array(p.axes)
    axes[pick] *= np.minimum(1.0, target / r_eq[pick])[:, None]
    return dataclasses.replace(p, axes=axes)


def size_classes(table, meta):
    """The class of each truth bubble (``truth.csv`` order) and the radius of the ball of its visible part's
    volume (``volume_in_fov_mm3``), pixels."""
    c = meta["column"]
    ball = np.cbrt(3 * table["volume_in_fov_mm3"] / (4 * np.pi)) / c["pixel_size_mm"]
    cut = (table["cut_top"] > 0) | (table["cut_bottom"] > 0)
    lo, hi = TARGET_BALL
    classes = np.where(ball < lo, "tiny", np.where(ball > hi, "large", np.where(cut, "cap", "small")))
    return classes, ball


def seeded(table, points):
    """(n,) bool: which truth ellipsoids hold at least one of ``points`` (k, 3), mm."""
    centres = np.stack([table[f"centre_{a}_mm"] for a in "xyz"], axis=1)
    axes = np.stack([table[f"semi_axis_{k}_mm"] for k in (1, 2, 3)], axis=1)
    rot = np.stack([table[f"rotation_{i}{j}"] for i in (1, 2, 3) for j in (1, 2, 3)], axis=1).reshape(-1, 3, 3)
    m = shape_matrices(axes, rot, power=-2)
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros(len(centres), bool)
    d = points[None, :, :] - centres[:, None, :]  # (n, k, 3)
    q = np.einsum("nki,nij,nkj->nk", d, m, d)
    return (q <= 1.0).any(axis=1)


def _simulate(folder, args):
    """The case's folder (``scan.h5``, ``truth.csv``, ``phantom.json``), made unless it holds the same case."""
    meta_path = folder / "phantom.json"
    key = {"phantom": args.phantom, "bubbles": args.bubbles, "seed": args.seed, "rows": args.rows,
           "cols": args.cols}
    key.update({"small_share": args.small_share, "small_range": list(args.small_range)} if args.phantom == "small"
               else {"subscan": args.subscan})
    if meta_path.is_file() and json.loads(meta_path.read_text()).get("detection") == key:
        return folder, None
    t0 = time.perf_counter()
    if args.phantom == "small":
        p = small_column(args.bubbles, seed=args.seed, rows=args.rows, cols=args.cols,
                         small_share=args.small_share, small_range=args.small_range)
        _, meta = write_column(folder, p, simulate_column(p))
    else:
        meta = flowing_subscan(folder, args.bubbles, args.subscan, seed=args.seed, rows=args.rows, cols=args.cols)
    meta["detection"] = key
    meta_path.write_text(json.dumps(meta, indent=2))
    return folder, time.perf_counter() - t0


def flowing_subscan(folder, n_bubbles, subscan, *, seed=0, rows=128, cols=384):
    """One subscan of the flowing foam (``bubsub simulate --phantom flowing3d``'s defaults) as a column folder.

    The whole scan is simulated (each projection at its own time: the foam
    moves, shrinks and grows during a subscan); ``scan.h5`` holds subscan
    ``subscan``'s projections, ``truth.csv`` its bubbles at its mid-time.

    Returns
    -------
    dict
        ``phantom.json``'s contents (a column's keys, which :mod:`bubsub.bench.matching` reads).
    """
    foam = flowing_foam(n_bubbles, seed=seed, rows=rows, cols=cols, subscans=FLOWING_DEFAULTS["subscans"])
    if not 0 <= subscan < FLOWING_DEFAULTS["subscans"]:
        raise ValueError(f"subscan must be in [0, {FLOWING_DEFAULTS['subscans']}), got {subscan}")
    whole = simulate_flowing(foam)
    p = whole.projections_per_subscan
    sl = slice(subscan * p, (subscan + 1) * p)
    folder.mkdir(parents=True, exist_ok=True)
    write_scan(folder / "scan.h5", Scan(data=whole.data[sl], geometry=whole.geometry[sl],
                                        background=whole.background[sl], bubble_contrast=whole.bubble_contrast,
                                        attrs=whole.attrs))
    c = foam.column
    rows_ = truth_rows(foam.at(subscan + 0.5), c.fov_half_height)
    write_csv(folder / "truth.csv", rows_, list(TRUTH_COLUMN_INFO), describe=TRUTH_COLUMN_INFO,
              title=f"flowing foam truth at subscan {subscan}'s mid-time")
    shape, extent = truth_grid(c)
    return {"phantom": "column", "ndim": 3, "seed": seed, "grid_shape": list(shape), "grid_extent": list(extent),
            "angles": p, "truth_table": "truth.csv", "bubbles": len(rows_),
            "column": {"radius_mm": c.radius, "fov_radius_mm": c.fov_radius, "fov_half_height_mm": c.fov_half_height,
                       "rows": c.rows, "cols": c.cols, "pixel_size_mm": c.pixel_size}}


def _per_class(classes, ok):
    return {k: (int(np.sum(ok & (classes == k))), int(np.sum(classes == k))) for k in CLASSES}


def _status(scores, n):
    """(n,) str: each truth bubble's status in ``match``'s rows (labels are ids + 1); absent ones 'absent'."""
    out = np.full(n, "absent", dtype=object)
    for label, _, _, status in scores["per_truth"]:
        out[label - 1] = status
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(prog="bubsub bench detection", description=__doc__.split("\n\n")[0])
    ap.add_argument("--phantom", choices=("small", "flowing"), default="small",
                    help="small: a column with a share of small bubbles; flowing: one subscan of the flowing foam")
    ap.add_argument("--subscan", type=int, default=0, help="flowing: which subscan (0-11)")
    ap.add_argument("--bubbles", type=int, default=150)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rows", type=int, default=128)
    ap.add_argument("--cols", type=int, default=384)
    ap.add_argument("--small-share", type=float, default=0.3)
    ap.add_argument("--small-range", type=float, nargs=2, default=(5.0, 13.0))
    ap.add_argument("--data", default="bench-detection", help="folder of the simulation (reused when the same)")
    ap.add_argument("--no-voxel", action="store_true", help="skip the voxel route")
    ap.add_argument("--seeds-only", action="store_true", help="count the seeds only (no reconstruction)")
    ap.add_argument("--sirt-iterations", type=int, default=100)
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="a ReconstructionSettings field")
    args = ap.parse_args(argv)
    folder = Path(args.data) / (f"small{args.bubbles}_seed{args.seed}" if args.phantom == "small"
                                else f"flowing{args.bubbles}_seed{args.seed}_subscan{args.subscan}")
    sim, sim_seconds = _simulate(folder, args)
    meta, tab = column_truth(sim)
    classes, ball = size_classes(tab, meta)
    settings = ReconstructionSettings(progress=False)
    for item in args.set:
        name, _, text = item.partition("=")
        settings = dataclasses.replace(settings, **{name: setting_value(text, getattr(settings, name))})
    scan = read_scan(sim / "scan.h5")
    c = meta["column"]
    print(f"column {sim}: {meta['bubbles']} bubbles in the rows ({int(np.sum(tab['cut_top'] > 0))} cut by the top, "
          f"{int(np.sum(tab['cut_bottom'] > 0))} by the bottom), {meta['angles']} x {c['rows']} x {c['cols']}"
          + ("" if sim_seconds is None else f", simulated in {sim_seconds:.0f} s"))
    rows_out = []  # (route, per truth bubble: its status, bubbles, seconds, scores or None)
    t0 = time.perf_counter()
    local = MeshProjector(scan.geometry, supersampling=settings.supersampling)
    surfaces = initial_bubbles(scan.bubble_data, scan.geometry, scan.bubble_contrast, local, settings)[0]
    seeds = np.array([s.fine().centroid for s in surfaces]).reshape(-1, 3)
    hit = seeded(tab, seeds)
    rows_out.append(("bubsub seeds", np.where(hit, "found", "missed"), len(seeds), time.perf_counter() - t0, None))
    truth = truth_labels(meta, tab)
    cut = (tab["cut_top"] > 0) | (tab["cut_bottom"] > 0)
    if not args.seeds_only:
        t0 = time.perf_counter()
        rec = reconstruct(scan, settings)
        seconds = time.perf_counter() - t0
        scores = match(truth, mesh_labels([s.fine() for s in rec.surfaces], meta), cut)
        adds = sum(1 for ch in (rec.report.get("topology") or {}).get("changes", []) if ch["change"] == "add")
        rows_out.append((f"bubsub reconstruct ({adds} added by topology)", _status(scores, len(classes)),
                         len(rec.surfaces), seconds, scores))
    if not args.no_voxel:
        t0 = time.perf_counter()
        labels = voxel_route(scan, meta, args.sirt_iterations)
        labels[~fov_mask(labels.shape, tuple(meta["grid_extent"]), (c["fov_radius_mm"], c["fov_half_height_mm"]))] = 0
        scores = match(truth, labels, cut)
        rows_out.append((f"SIRT {args.sirt_iterations} + Otsu + watershed", _status(scores, len(classes)),
                         scores["reconstructed"], time.perf_counter() - t0, scores))
    print("\nper class, truth bubbles seeded (a seed inside the truth ellipsoid) or found (IoU >= 0.5, not merged):\n")
    header = ["route", "bubbles"] + [f"{k} ({np.sum(classes == k)})" for k in CLASSES] + ["seconds"]
    body = [[name, str(n)] + [f"{a} ({100 * a / max(b, 1):.0f} %)" for a, b in (_per_class(classes, st == "found")[k]
                                                                              for k in CLASSES)]
            + [f"{sec:.0f}"] for name, st, n, sec, _ in rows_out]
    print(table(header, body))
    keys = ("truth", "found", "missed", "merged", "spurious", "cut_truth", "cut_found")
    body = [[name] + [str(r[k]) for k in keys] + [f"{r['ddi']:.4f}"] for name, _, _, _, r in rows_out if r]
    if body:
        print()
        print(table(["route", "truth", "found", "missed", "merged", "spurious", "cut", "cut found", "DDI in FOV"],
                    body))
    lo, hi = TARGET_BALL
    for name, st, _, _, r in rows_out[1:]:
        lost = [i for i in np.flatnonzero(classes != "large") if st[i] != "found"]
        if lost:
            print(f"\n{name}, bubbles under {hi:g} px not found (truth id: class, ball radius px, seeded, status):")
            print("  " + "; ".join(f"{int(tab['id'][i])}: {classes[i]} {ball[i]:.1f} {'yes' if hit[i] else 'no'} "
                                   f"{st[i]}" for i in lost))
    print(f"\nclasses by the ball of the visible part's volume: small/cap {lo:g}-{hi:g} px (cap: cut by the top or "
          f"bottom row), tiny < {lo:g} px, large > {hi:g} px")
    return 0
