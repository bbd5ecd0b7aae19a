"""The paper's simulation experiments (the demo is in :mod:`.demo`).

``bubsub experiment NAME --out DIR [--quick]`` writes ``NAME.csv`` (one row per
method, setting and seed) and ``NAME.png`` (mean Dice dissimilarity per method).

* ``fig1a``: 2D foam, DDI against the number of projections (I0 = 1e4).
* ``fig1b``: 2D foam, DDI against the photon count (150 projections).
* ``fig5``: 2D foam, BubSub's DDI against the initial radius (25 projections, I0 = 1e4).
* ``fig3a``: 3D foam, DDI against the number of cone-beam projections (I0 = 1e4).
* ``dense2d`` / ``dense3d``: dense wet foam (:mod:`bubsub.core.foam.dense`, gas
  fraction about 0.7, films of a few voxels), DDI against the number of projections.

Every voxel baseline (FBP/FDK, SIRT, CGLS, TV) reconstructs the bubble data
(scan minus background) on the evaluation grid and is binarised by Otsu's
threshold and a morphological opening; BubSub's meshes are rasterised on the
same grid. Seeds fix the phantom and the noise of every run.
"""

from __future__ import annotations

import csv
import json
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from bubsub.core.io.atomic import atomic_path, atomic_write_text
from bubsub.core.metrics import dice_dissimilarity
from bubsub.core.projection.masks import bubble_mask

from bubsub.clients.experiments.folders import check_experiment_folder, finish_experiment
from bubsub.clients.cluster.engine import run_tasks
from bubsub.clients.pipeline.results.figures import subplots
from bubsub.clients.progress import phase
from bubsub.core import ScanGeometry
from bubsub.core.foam import phantoms, simulate
from bubsub.core.io.tables import write_table
from bubsub.core.voxel.astra2d import reconstruct_2d
from bubsub.core.voxel.reconstruct3d import reconstruct_3d
from bubsub.core.voxel.segment import binarise

__all__ = ["EXPERIMENTS", "run_experiment", "run_case", "run_setting", "case_config", "simulate_case",
           "baseline_mask"]

#: TV weights tried per run; the one with the lowest DDI is kept (as the paper picks
#: the weight that minimises the error)
TV_WEIGHTS = (1e-3, 3e-3, 1e-2)


@dataclass(frozen=True)
class Experiment:
    name: str
    ndim: int
    variable: str  # "angles", "photons" or "radius"
    values: tuple
    quick_values: tuple
    methods: tuple
    angles: int = 25
    photons: float = 1e4
    title: str = ""
    phantom: str = "sparse"  # "sparse" (foam2d/foam3d) or "dense" (core.foam.dense)


EXPERIMENTS = {
    "fig1a": Experiment("fig1a", 2, "angles", (10, 25, 50, 100, 150, 300), (10, 25),
                        ("fbp", "sirt", "cgls", "tv", "bubsub"), title="2D: Dice dissimilarity vs projections (I0 = 1e4)"),
    "fig1b": Experiment("fig1b", 2, "photons", (1e2, 1e3, 1e4, 1e5), (1e3, 1e4),
                        ("fbp", "sirt", "cgls", "tv", "bubsub"), angles=150,
                        title="2D: Dice dissimilarity vs photon count (150 projections)"),
    "fig5": Experiment("fig5", 2, "radius", (0.25, 0.5, 0.75, 1.0, 1.5, 2.0), (0.5, 1.0, 2.0), ("bubsub",),
                       title="2D: BubSub vs initial radius (x mean bubble radius; 25 projections, I0 = 1e4)"),
    "fig3a": Experiment("fig3a", 3, "angles", (10, 25, 50, 100), (10, 25),
                        ("fdk", "sirt", "cgls", "tv", "bubsub"), title="3D: Dice dissimilarity vs projections (I0 = 1e4)"),
    "dense2d": Experiment("dense2d", 2, "angles", (10, 25, 50, 100), (10, 25),
                          ("fbp", "sirt", "cgls", "tv", "bubsub"), phantom="dense",
                          title="2D dense wet foam: Dice dissimilarity vs projections (I0 = 1e4)"),
    "dense3d": Experiment("dense3d", 3, "angles", (10, 25, 50), (10, 25),
                          ("fdk", "sirt", "cgls", "tv", "bubsub"), phantom="dense",
                          title="3D dense wet foam: Dice dissimilarity vs projections (I0 = 1e4)"),
}

# quick mode shrinks the problems so a whole experiment runs in about a minute
QUICK_2D = {"n_bubbles": 12, "det_count": 600, "image_size": 800, "grid": 256, "iterations": 40}
FULL_2D = {"n_bubbles": 40, "det_count": 2400, "image_size": 2000, "grid": 512, "iterations": 80}
QUICK_3D = {"n_bubbles": 12, "det_cols": 128, "voxel": 0.25, "iterations": 40}
FULL_3D = {"n_bubbles": 60, "det_cols": 512, "voxel": 0.1, "iterations": 80}


def case_config(exp, quick):
    """Problem sizes of experiment ``exp`` (phantom, detector, grid, iterations), quick or full."""
    cfg = (QUICK_2D if quick else FULL_2D) if exp.ndim == 2 else (QUICK_3D if quick else FULL_3D)
    if exp.phantom == "dense" and exp.ndim == 3 and quick:
        cfg = dict(cfg, voxel=cfg["voxel"] / 2)  # films of two voxels need a finer grid than 0.25 mm
    return cfg


def simulate_case(ndim, seed, angles, photons, cfg, quick, dense=False):
    """``(phantom, scan, grid shape, grid extent)`` of one run: the seed's foam, its scan and DDI grid."""
    from bubsub.core.foam import dense as dense_foams  # scipy.optimize, which bubsub --help does not import

    if ndim == 2:
        size = 5.0 if quick else 10.0
        if dense:  # films of 0.08 mm: 4 pixels of the evaluation grid in both modes
            ph = dense_foams.dense_foam2d(seed, n_bubbles=cfg["n_bubbles"], size=size)
        else:
            ph = phantoms.foam2d(seed, n_bubbles=cfg["n_bubbles"], **({"size": size, "radius_range": (0.25, 0.6)} if quick else {}))
        # a detector 1.44 x the square's side sees the whole square at every angle
        g = simulate.default_geometry_2d(angles, det_count=cfg["det_count"], pixel_size=1.44 * size / cfg["det_count"])
        scan = simulate.simulate_2d(ph, g, photons=photons, seed=seed, image_size=cfg["image_size"])
        shape, extent = ph.grid(cfg["grid"])
    else:
        size = (8.0, 8.0, 4.0) if quick else (20.0, 20.0, 10.0)
        if dense:  # films and Plateau borders two voxels of the evaluation grid thick
            ph = dense_foams.dense_foam3d(seed, n_bubbles=cfg["n_bubbles"], size=size, film=2 * cfg["voxel"],
                                          border=2 * cfg["voxel"], margin=0.1)
        else:
            ph = phantoms.foam3d(seed, n_bubbles=cfg["n_bubbles"], size=size)

        cols = cfg["det_cols"]
        pixel = (size[0] * 1.5) / cols
        g = ScanGeometry.cone(np.linspace(0, 2 * np.pi, angles, endpoint=False), source_origin=300.0,
                              origin_detector=15.0, pixel_size=pixel, cols=cols, rows=cols // 2)
        scan = simulate.simulate_3d(ph, g, photons=photons, seed=seed)
        shape = tuple(int(round(s / cfg["voxel"])) for s in size[::-1])
        shape, extent = ph.grid(shape)
    return ph, scan, shape, extent


def baseline_mask(method, scan, shape, extent, ndim, tv_weight=None):
    """The binarised voxel reconstruction (``fbp``/``fdk``, ``sirt``, ``cgls``, ``tv``) of a scan's bubble data."""
    data = scan.bubble_data
    kw = {"tv_weight": tv_weight} if method == "tv" else {}
    if ndim == 2:
        img = reconstruct_2d(method, data, scan.geometry, shape, extent, **kw)
    else:
        img = reconstruct_3d(method, data, scan.geometry, shape, extent, **kw)
    # bubbles carry the sign of the contrast in the bubble data
    return binarise(np.sign(scan.bubble_contrast) * img, bubbles_are_dark=False)


def _setting(exp, value, quick):
    """``(angles, photons)`` of one swept value."""
    # quick mode keeps to 25 views, so that the photon sweep stays quick too
    angles = int(value) if exp.variable == "angles" else (min(exp.angles, 25) if quick else exp.angles)
    photons = float(value) if exp.variable == "photons" else exp.photons
    return angles, photons


@lru_cache(maxsize=1)
def _simulated(name, seed, angles, photons, quick):
    # the methods of one (value, seed) run one after the other here: simulate once for all of them
    exp = EXPERIMENTS[name]
    return simulate_case(exp.ndim, seed, angles, photons, case_config(exp, quick), quick, exp.phantom == "dense")


def run_setting(name, value, seed, method, quick):
    """One result row of experiment ``name``: ``method`` at ``value`` on the phantom of ``seed``.

    A self-contained task (module-level, picklable arguments, simulates its
    own scan from the seed), so that it runs the same here or on a Dask worker.
    """
    exp = EXPERIMENTS[name]
    ph, scan, shape, extent = _simulated(name, seed, *_setting(exp, value, quick), quick)
    kw = {"iterations": case_config(exp, quick)["iterations"]}
    if exp.variable == "radius":
        kw.update(radius=float(value) * float(np.mean(ph.radii)), estimate_radii=False)
    ddi, sec = run_case(method, scan, ph, shape, extent, **kw)
    return {"experiment": name, exp.variable: value, "method": method, "seed": seed,
            "ddi": ddi, "seconds": sec, "quick": quick}


def run_case(method, scan, phantom, shape, extent, *, iterations=80, radius=None, estimate_radii=True):
    """DDI of one method on one simulated scan: ``(ddi, seconds)``."""
    t = time.perf_counter()
    truth = bubble_mask(phantom.bubbles, shape, extent)
    if method == "bubsub":
        from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, reconstruct

        rec = reconstruct(scan, ReconstructionSettings(iterations=iterations, radius=radius,
                                                       estimate_radii=estimate_radii, progress=False))
        if rec.report["interrupted"]:  # Ctrl-C inside a fit stops the experiment, not just this fit
            raise KeyboardInterrupt
        mask = bubble_mask(rec.surfaces, shape, extent)
    elif method == "tv":
        return min(dice_dissimilarity(baseline_mask(method, scan, shape, extent, phantom.ndim, w), truth)
                   for w in TV_WEIGHTS), time.perf_counter() - t
    else:
        mask = baseline_mask(method, scan, shape, extent, phantom.ndim)
    return dice_dissimilarity(mask, truth), time.perf_counter() - t


def run_experiment(name, out, *, quick=False, seeds=None, values=None, methods=None, resume=False, overwrite=False,
                   progress=True, client=None):
    """Run one experiment; write ``NAME.csv``, ``NAME.png`` and ``NAME.json`` (summary) into ``out``.

    ``out`` follows the experiment folders' policy (:mod:`.folders`): it may
    hold other experiments, but this experiment's earlier results only with
    ``resume`` or ``overwrite``.

    Parameters
    ----------
    values : sequence of float, optional
        The settings swept (projections, photon counts or radius factors)
        instead of the paper's.
    methods : sequence of str, optional
        A subset of the experiment's methods.
    resume : bool
        Keep the runs already in ``out/NAME.csv`` (same mode) and run only the
        missing (value, seed, method) cases; the CSV, summary and plot then
        cover all of them. Lets a long experiment continue after Ctrl-C.
    overwrite : bool
        Replace this experiment's earlier results in ``out`` (or another
        command's results there).
    client : dask.distributed.Client, optional
        Run the cases as tasks on this cluster (one task per value, seed and
        method; :func:`run_setting`); ``None`` runs them here, in order.
    """
    if name not in EXPERIMENTS:
        raise ValueError(f"unknown experiment {name!r}; choose one of {sorted(EXPERIMENTS)}")
    exp = EXPERIMENTS[name]
    methods = tuple(methods) if methods else exp.methods
    unknown = sorted(set(methods) - set(exp.methods))
    if unknown:
        raise ValueError(f"{name} has no method(s) {unknown}; choose from {list(exp.methods)}")
    out = check_experiment_folder(out, name, overwrite=overwrite, resume=resume)
    out.mkdir(parents=True, exist_ok=True)
    # floats throughout, so resumed and new runs of one setting share a key
    values = tuple(float(v) for v in (values or (exp.quick_values if quick else exp.values)))
    seeds = seeds or (1 if quick else 10)
    rows = _read_runs(out / f"{name}.csv", exp.variable, quick) if resume else []
    done = {(r[exp.variable], r["seed"], r["method"]) for r in rows}
    todo = [(v, s, m) for v in values for s in range(seeds) for m in methods if (v, s, m) not in done]

    bar = phase(name, len(todo), unit="run", enabled=progress, each=True)
    t0 = time.perf_counter()
    done_now = {}

    def finished(i, row):
        done_now[i] = row
        bar.update(1, method=row["method"], ddi=f"{row['ddi']:.3f}")

    interrupted = False
    try:
        run_tasks(client, run_setting, [(name, v, s, m, quick) for v, s, m in todo], on_result=finished)
    except KeyboardInterrupt:
        interrupted = True
        print(f"{name}: interrupted; writing the {len(rows) + len(done_now)} finished runs")
    finally:
        bar.close()
    # task order, whatever order a cluster finished them in
    rows += [done_now[i] for i in sorted(done_now)]
    summary = summarise(rows, exp.variable)
    summary["seconds_runs"] = float(np.nansum([float(r["seconds"]) for r in rows]))  # all runs, resumed ones too
    summary["seconds_this_call"] = time.perf_counter() - t0
    summary["quick"] = quick
    summary["interrupted"] = interrupted
    summary["seeds"] = sorted({int(r["seed"]) for r in rows})
    _write_csv(out / f"{name}.csv", rows, exp.variable)
    atomic_write_text(out / f"{name}.json", json.dumps(summary, indent=2))
    plot(out / f"{name}.png", summary, exp)
    finish_experiment(out, name, [out / f"{name}{ext}" for ext in (".csv", ".csv-metadata.json", ".json", ".png")])
    print(format_table(summary, exp.variable))
    return summary


def _read_runs(path, variable, quick):
    """The runs of an earlier CSV, for ``resume``; refuses a CSV of the other mode."""
    if not path.exists():
        return []
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        missing = {variable, "method", "seed", "ddi"} - set(r)
        if missing:
            raise ValueError(f"{path} is not a results CSV of this experiment (no column(s) {sorted(missing)})")
        was_quick = r.get("quick", "False") == "True"
        if was_quick != quick:
            raise ValueError(f"{path} holds {'quick' if was_quick else 'full'}-mode runs; resume it in the same mode")
        r.update({variable: float(r[variable]), "seed": int(r["seed"]), "ddi": float(r["ddi"]),
                  "seconds": float(r.get("seconds") or "nan"), "quick": was_quick})
    return rows


def summarise(rows, variable):
    """Mean and standard deviation of the DDI per (method, value)."""
    table = {}
    for r in sorted(rows, key=lambda r: float(r[variable])):
        table.setdefault(r["method"], {}).setdefault(r[variable], []).append(r["ddi"])
    return {
        "variable": variable,
        "methods": {
            m: {str(v): {"mean": float(np.mean(d)), "std": float(np.std(d)), "n": len(d)} for v, d in vals.items()}
            for m, vals in table.items()
        },
    }


def format_table(summary, variable):
    methods = list(summary["methods"])
    values = list(next(iter(summary["methods"].values())).keys()) if methods else []
    head = f"{variable:>10} | " + " | ".join(f"{m:>8}" for m in methods)
    lines = [head, "-" * len(head)]
    for v in values:
        cells = [summary["methods"][m].get(v, {}).get("mean", float("nan")) for m in methods]
        lines.append(f"{v:>10} | " + " | ".join(f"{c:8.4f}" for c in cells))
    return "\n".join(lines)


#: What the experiments' variables are: ``variable: (unit, meaning)``.
VARIABLE_INFO = {"angles": ("1", "number of projections"), "photons": ("1", "incident photons per detector pixel"),
                 "radius": ("1", "initial radius / mean bubble radius")}


def _write_csv(path, rows, variable):
    """``NAME.csv`` and its CSVW sidecar (:func:`bubsub.core.io.tables.write_table`)."""
    info = {"experiment": ("", "experiment name"), variable: VARIABLE_INFO[variable],
            "method": ("", "reconstruction method"), "seed": ("", "seed of the simulated phantom and noise"),
            "ddi": ("1", "Dice dissimilarity index against the truth (0 is perfect)"),
            "seconds": ("s", "wall-clock time of the reconstruction"),
            "quick": ("", "True for a quick-mode run (fewer values, seeds and iterations)")}
    return write_table(path, [{c: r[c] for c in info} for r in rows], info,
                       title=f"{Path(path).stem}: DDI per {variable}, method and seed")


#: one colour per method in every plot
_COLOURS = {"fbp": "C0", "fdk": "C0", "sirt": "C1", "cgls": "C2", "tv": "C3", "bubsub": "C4"}


def plot(path, summary, exp):
    fig, ax = subplots(figsize=(6.5, 4.5), dpi=110)
    for m, vals in summary["methods"].items():
        x = np.array([float(v) for v in vals])
        y = np.array([vals[v]["mean"] for v in vals])
        e = np.array([vals[v]["std"] for v in vals])
        ax.errorbar(x, y, yerr=e, marker="o", capsize=3, color=_COLOURS.get(m), label=m.upper() if m != "bubsub" else "BubSub")
    if exp.variable in ("angles", "photons"):
        # DDIs span two decades: log axes keep BubSub's curve readable
        ax.set_xscale("log")
        ax.set_yscale("log")
        ticks = sorted({float(v) for vals in summary["methods"].values() for v in vals})
        ax.set_xticks(ticks)
        ax.set_xticklabels([f"{t:g}" for t in ticks])
        ax.minorticks_off()
    ax.set_xlabel({"angles": "number of projections", "photons": "photon count I0",
                   "radius": "initial radius / mean bubble radius"}[exp.variable])
    ax.set_ylabel("Dice dissimilarity")
    ax.set_title(exp.title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
