"""Paper figures 6 and 7: 4D BubSub against voxel baselines on an expanding foam.

``bubsub experiment fig6 --out DIR [--quick]`` (2D) or ``fig6-3d`` (cone beam):

1. simulate an expanding foam (:mod:`bubsub.core.foam.expanding`), updated
   between every projection, into ``DIR/sim``;
2. ``reconstruct4d`` it with the odd projections of each subscan held out,
   into ``DIR/bubsub``;
3. per subscan, on the same fitted projections: the paper's voxel baseline
   (30 Barzilai-Borwein iterations, x >= 0) and SIRT, each binarised by Otsu's
   threshold and an opening, scored by DDI against the truth at the
   subscan's mid-time; held-out projection MSE for BubSub and BB.

Writes ``fig6.csv`` (one row per subscan and method, with its CSVW sidecar), ``fig6.json`` (means,
ratio to SIRT + Otsu, fraction of rows on the right track, seconds),
``fig6.png`` (held-out MSE and DDI per subscan) and ``fig7.png`` (BB slice,
its Otsu binarisation, BubSub, truth at four subscans).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from bubsub.core.io.atomic import atomic_path, atomic_write_text
from bubsub.clients.experiments.folders import check_experiment_folder, finish_experiment
from bubsub.clients.experiments.runner import baseline_mask
from bubsub.clients.pipeline.evaluation.evaluate4d import evaluate_dynamic
from bubsub.clients.pipeline.results.figures import subplots
from bubsub.clients.pipeline.evaluation.simulation import simulate_dynamic_to_dir
from bubsub.core.io.meshio import read_ply, read_polygons_json
from bubsub.core.io.scanfile import read_scan
from bubsub.core.io.tables import write_table
from bubsub.core.metrics import dice_dissimilarity
from bubsub.core.projection.masks import bubble_mask, check_grid
from bubsub.core.voxel.segment import binarise

__all__ = ["FIG6_CONFIGS", "FIG6_COLUMN_INFO", "run_fig6"]

#: ``column: (unit, meaning)`` of ``fig6.csv``.
FIG6_COLUMN_INFO = {
    "subscan": ("", "subscan index"),
    "method": ("", "bubsub, bb (30 Barzilai-Borwein iterations, x >= 0) or sirt, voxel baselines binarised by Otsu"),
    "start": ("", "bubsub: cold (from a voxel preview) or warm (from the neighbouring subscan); empty otherwise"),
    "iterations": ("1", "iterations of the fit or of the voxel baseline"),
    "stop_reason": ("", "bubsub: why the fit stopped"),
    "ddi": ("1", "Dice dissimilarity index against the truth at the subscan's mid-time (0 is perfect)"),
    "holdout_mse": ("1", "mean squared error on the held-out (odd) projections; empty for sirt"),
    "seconds": ("s", "wall-clock time of the subscan's reconstruction"),
    "cpu_seconds": ("s", "bubsub: CPU time of the subscan's reconstruction"),
}

FIG6_CONFIGS = {
    # 2D: the target setting (>= 25 bubbles, 8 subscans of 25 + 25 parallel projections, I0 1e4)
    (2, False): {"bubbles": 30, "subscans": 8, "per_subscan": 50, "det_count": 2400, "iterations": 80, "grid": 512},
    (2, True): {"bubbles": 6, "subscans": 2, "per_subscan": 16, "det_count": 200, "iterations": 20, "grid": 128},
    # 3D: the paper's 25 + 25 cone projections per subscan on a smaller detector and foam
    (3, False): {"bubbles": 20, "subscans": 20, "per_subscan": 50, "det_count": 256, "iterations": 80, "voxel": 0.2},
    (3, True): {"bubbles": 6, "subscans": 2, "per_subscan": 16, "det_count": 96, "iterations": 20, "voxel": 0.4},
}


def _grid(meta, cfg):
    size = np.asarray(meta["size"], float)
    if meta["ndim"] == 2:
        n = cfg["grid"]
        return check_grid((n, n), (-size[0] / 2, size[0] / 2, -size[1] / 2, size[1] / 2))
    shape = tuple(int(round(s / cfg["voxel"])) for s in size[::-1])
    ext = []
    for s in size:
        ext += [-s / 2, s / 2]
    return check_grid(shape, tuple(ext))


def _sirt_mask(scan, shape, extent):
    return baseline_mask("sirt", scan, shape, extent, scan.ndim)


def _score_subscan(sim_dir, rec_dir, k, shape, extent, report_k):
    """Rows (BubSub, BB, and in 2D SIRT) of subscan ``k`` and its fig. 7 images; runs in a worker process."""
    from bubsub.core.io.subscans import subscan, subscan_layout

    from bubsub.clients.pipeline.evaluation.voxel_baseline import BB_ITERATIONS, voxel_baseline

    scan = read_scan(Path(sim_dir) / "scan.h5")
    ndim = scan.ndim
    reader, ext = (read_polygons_json, ".json") if ndim == 2 else (read_ply, ".ply")
    sub = subscan(scan, subscan_layout(scan), k)
    truth = bubble_mask(reader(Path(sim_dir) / "truth" / f"subscan_{k:04d}{ext}"), shape, extent)
    bb = voxel_baseline(sub, "odd", shape=shape, extent=extent)
    bb_mask = binarise(bb["image"], bubbles_are_dark=False)
    rec = bubble_mask(reader(Path(rec_dir) / f"subscan_{k:04d}" / f"bubbles{ext}"), shape, extent)
    rows = [
        {"subscan": k, "method": "bubsub", "ddi": dice_dissimilarity(rec, truth),
         "holdout_mse": report_k["holdout_mse"], "seconds": report_k["seconds"], "start": report_k["start"],
         "iterations": report_k["iterations"], "stop_reason": report_k.get("stop_reason"),
         "cpu_seconds": report_k.get("cpu_seconds")},
        {"subscan": k, "method": "bb", "ddi": dice_dissimilarity(bb_mask, truth), "holdout_mse": bb["holdout_mse"],
         "seconds": bb["seconds"], "start": "", "iterations": BB_ITERATIONS},
    ]
    if ndim == 2:  # SIRT 200 iterations + Otsu, the 2D reference (too slow to run per 3D subscan)
        t_sirt = time.perf_counter()
        sirt_mask = _sirt_mask(sub.subset(slice(0, None, 2)), shape, extent)
        rows.append({"subscan": k, "method": "sirt", "ddi": dice_dissimilarity(sirt_mask, truth),
                     "holdout_mse": None, "seconds": time.perf_counter() - t_sirt, "start": ""})
    return rows, (bb["image"], bb_mask, rec, truth)


def _simulated(sim_dir, cfg, ndim, seed, photons):
    """The metadata of an earlier simulation in ``sim_dir`` made with these settings, else None."""
    path = Path(sim_dir) / "phantom.json"
    if not (path.is_file() and (Path(sim_dir) / "scan.h5").is_file()):
        return None
    meta = json.loads(path.read_text())
    want = {"ndim": ndim, "seed": seed, "photons": photons, "bubbles": cfg["bubbles"], "subscans": cfg["subscans"],
            "projections_per_subscan": cfg["per_subscan"], "det_count": cfg["det_count"]}
    return meta if all(meta.get(k) == v for k, v in want.items()) else None


def run_fig6(out, *, ndim=2, quick=False, seed=0, photons=1e4, progress=True, config=None, jobs=1, resume=True,
             overwrite=False):
    """Run the experiment into ``out``; returns the summary dict (also ``fig6.json``).

    ``config`` overrides entries of :data:`FIG6_CONFIGS` (e.g. ``{"subscans": 10}``).
    With ``resume``, a simulation and the complete subscans of an earlier run
    in ``out`` with the same settings are reused; without it, a folder
    holding an earlier fig6 run is refused unless ``overwrite``, which
    simulates and reconstructs again (the experiment folders' policy,
    :mod:`.folders`). ``jobs`` > 1 scores the subscans (voxel baselines,
    DDI) in that many processes.

    Ctrl-C in a fit stops the run: the finished subscans stay in
    ``out/bubsub`` (``resume`` continues them), nothing is scored, and the
    summary is ``{"interrupted": True, "subscans": [...]}``.
    """
    from bubsub.clients.pipeline.dynamic4d.chain import DynamicSettings
    from bubsub.clients.pipeline.reconstruct4d import reconstruct_dynamic


    name = "fig6" if ndim == 2 else "fig6-3d"
    cfg = dict(FIG6_CONFIGS[(ndim, bool(quick))], **(config or {}))
    out = check_experiment_folder(out, name, overwrite=overwrite, resume=resume)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    kw = {"size": 5.0, "radius_range": (0.25, 0.6)} if quick and ndim == 2 else {}
    meta = _simulated(out / "sim", cfg, ndim, seed, photons) if resume else None
    if meta is None:
        _, _, meta = simulate_dynamic_to_dir(
            out / "sim", "expanding2d" if ndim == 2 else "expanding3d", subscans=cfg["subscans"],
            projections_per_subscan=cfg["per_subscan"], photons=photons, seed=seed, det_count=cfg["det_count"],
            n_bubbles=cfg["bubbles"], foam=kw)
        meta["det_count"] = cfg["det_count"]
        atomic_write_text(out / "sim" / "phantom.json", json.dumps(meta, indent=2))
    t_sim = time.perf_counter() - t0
    scan = read_scan(out / "sim" / "scan.h5")
    # config "warm_rtol": the warm fits' plateau stop (0: every warm fit runs all iterations)
    settings = DynamicSettings(iterations=cfg["iterations"], holdout="odd", progress=progress,
                               **{k: cfg[k] for k in ("warm_rtol",) if k in cfg})
    rec_dir = out / "bubsub"
    report = reconstruct_dynamic(scan, rec_dir, settings, resume=resume and rec_dir.exists(), overwrite=not resume)
    kept = [f for d in ("sim", "bubsub") for f in sorted((out / d).rglob("*")) if f.is_file()]
    if report["interrupted"]:  # Ctrl-C in a fit: keep the finished subscans for a resumed run, score nothing
        finish_experiment(out, name, kept)
        return {"interrupted": True, "subscans": [p["subscan"] for p in report["subscans"]]}
    shape, extent = _grid(meta, cfg)
    score = evaluate_dynamic(rec_dir, out / "sim", grid=(shape, extent))
    per = {p["subscan"]: p for p in report["subscans"]}
    ks = sorted(per)
    args = [(out / "sim", rec_dir, k, shape, extent, per[k]) for k in ks]
    if jobs > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(jobs) as pool:
            scored = list(pool.map(_score_subscan, *zip(*args)))
    else:
        scored = [_score_subscan(*a) for a in args]
    show = {ks[int(round(i))] for i in np.linspace(0, len(ks) - 1, min(4, len(ks)))}
    rows = [r for rs, _ in scored for r in rs]
    panels = {k: imgs for k, (_, imgs) in zip(ks, scored) if k in show}
    summary = _summarise(rows, score, report, t_sim, time.perf_counter() - t0, cfg, ndim, quick, seed, photons)
    finish_experiment(out, name, kept + _write(out, rows, summary, panels, extent))
    return summary


def _summarise(rows, score, report, t_sim, t_total, cfg, ndim, quick, seed, photons):
    def mean(method, key):
        vals = [r[key] for r in rows if r["method"] == method and r[key] is not None]
        return float(np.mean(vals)) if vals else None

    def seconds(start, key="seconds"):
        return [r[key] for r in rows if r["method"] == "bubsub" and r["start"] == start and r.get(key) is not None]

    warm, cold = seconds("warm"), seconds("cold")
    warm_cpu, cold_cpu = seconds("warm", "cpu_seconds"), seconds("cold", "cpu_seconds")
    ddi = {m: mean(m, "ddi") for m in ("bubsub", "bb", "sirt")}
    return {
        "ndim": ndim, "quick": quick, "seed": seed, "photons": photons, "config": cfg,
        "mean_ddi": ddi, "ddi_ratio_bubsub_to_sirt_otsu": ddi["bubsub"] / ddi["sirt"] if ddi["sirt"] else None,
        "mean_holdout_mse": {m: mean(m, "holdout_mse") for m in ("bubsub", "bb")},
        "right_track_fraction": score["right_track_fraction"], "track_rows": score["rows"],
        "seconds_cold": float(np.sum(cold)) if cold else None,
        "seconds_warm_median": float(np.median(warm)) if warm else None,
        "warm_to_cold_time": float(np.median(warm) / np.sum(cold)) if warm and cold else None,
        "cpu_seconds_cold": float(np.sum(cold_cpu)) if cold_cpu else None,
        "cpu_seconds_warm_median": float(np.median(warm_cpu)) if warm_cpu else None,
        "warm_to_cold_cpu_time": float(np.median(warm_cpu) / np.sum(cold_cpu)) if warm_cpu and cold_cpu else None,
        "tracks_ended": report["totals"]["tracks_ended"], "seconds_simulation": t_sim, "seconds_total": t_total,
        "interrupted": False,
    }


def _write(out, rows, summary, panels, extent):
    """Write fig6.csv, fig6.json, fig6.png and fig7.png; returns their paths."""
    write_table(out / "fig6.csv", [{c: r.get(c) for c in FIG6_COLUMN_INFO} for r in rows], FIG6_COLUMN_INFO,
                title="4D BubSub against voxel baselines per subscan (paper figure 6)")
    atomic_write_text(out / "fig6.json", json.dumps(summary, indent=2))

    fig, (a, b) = subplots(1, 2, figsize=(11, 4), dpi=100)
    for m, label in (("bubsub", "BubSub"), ("bb", "voxel BB (30 it., x >= 0)"), ("sirt", "SIRT + Otsu")):
        sel = [r for r in rows if r["method"] == m]
        if m != "sirt":
            a.plot([r["subscan"] for r in sel], [r["holdout_mse"] for r in sel], marker="o", ms=3, label=label)
        b.plot([r["subscan"] for r in sel], [r["ddi"] for r in sel], marker="o", ms=3,
               label=label if m != "bb" else "BB + Otsu")
    a.set_yscale("log")
    a.set_xlabel("subscan")
    a.set_ylabel("held-out projection MSE")
    a.legend(fontsize=8)
    b.set_xlabel("subscan")
    b.set_ylabel("Dice dissimilarity")
    b.legend(fontsize=8)
    with atomic_path(out / "fig6.png") as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")

    fig, axes = subplots(len(panels), 4, figsize=(10, 2.6 * len(panels)), dpi=90, squeeze=False)
    for row, (k, imgs) in zip(axes, sorted(panels.items())):
        for ax, img, title in zip(row, imgs, ("voxel BB", "BB + Otsu", "BubSub", "truth")):
            sl = img[img.shape[0] // 2] if img.ndim == 3 else img
            ax.imshow(sl, cmap="gray", extent=extent[:4])
            ax.set_title(f"{title}, subscan {k}", fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
    with atomic_path(out / "fig7.png") as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
    return [out / n for n in ("fig6.csv", "fig6.csv-metadata.json", "fig6.json", "fig6.png", "fig7.png")]
