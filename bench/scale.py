"""``bubsub bench scale``: ``bubsub reconstruct`` on simulated foam columns of ~150, ~600 and ~2400 bubbles.

For each case the column (:mod:`bubsub.core.foam.column`: 40 parallel
projections of 256 x 768 pixels of 12 um, rotated polydisperse ellipsoids in
a liquid cylinder at a gas fraction of 0.4, cut by the top and bottom rows,
exact chords with 2 x 2 sub-rays, Poisson noise at I0 = 1e4) is simulated
with ``bubsub simulate --phantom column`` into ``DATA/columnN`` (an existing
folder made with the same settings is reused), then ``bubsub reconstruct``
runs on it with its defaults in a child process, ``--repeats`` times
(options this benchmark does not know, e.g. ``--workers 2``, are passed on
to it). Measured per run: the wall time, the CPU time (``os.wait4``), the
peak resident memory summed over the child and all its descendants (Dask
workers included; psutil polled every 0.2 s), each phase's wall seconds
(``report.json``'s ``seconds_parts``), the DDI of ``bubsub evaluate``, and
the bubbles found, missed, merged and spurious inside the field of view
(:mod:`bubsub.bench.matching`, IoU >= 0.5), all truth bubbles and the cut
ones. Printed: one table per case (runs and median), the growth of cost
between cases, and a projection to one tomo_00080 subscan (300 x 1800 x
2016 pixels, and 2x binned) on 1 and 16 Dask workers.

The projection takes the measured cost per slab (``report.json``'s
``slabs``; a run without them counts as one slab of all its rows) and two
models: cost proportional to slab pixels x bubbles in the slab (each change
evaluated on its whole slab) and cost proportional to slab pixels only
(each change evaluated on its own footprint). The subscan is cut into slabs
of as many rows (halved when binned), its bubbles are as many per pixel
volume as in the measured column unless ``--tomo-bubbles`` says otherwise,
and W workers take ``ceil(slabs / W)`` rounds of slabs.

``python -m bubsub.bench scale [--cases 150,600,2400] [--repeats 1] [--data DIR] [--out DIR] [RECONSTRUCT OPTIONS]``
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from bubsub.bench.reconstruct import PHASES
from bubsub.bench.reconstruct import cli_command as _cli
from bubsub.core.foam.column import COLUMN_PRESETS
from bubsub.bench.matching import column_truth, match, mesh_labels, truth_labels
from bubsub.clients.pipeline.evaluation.evaluate import evaluate_dir
from bubsub.clients.pipeline.regions.slabs import halo_rows
from bubsub.core.io.meshio import read_ply

__all__ = ["main", "run_tree", "simulate_case", "score_case", "project", "table", "TOMO_00080"]

#: One subscan of TomoBank tomo_00080: projections, detector rows, detector columns.
TOMO_00080 = (300, 1800, 2016)
POLL_SECONDS = 0.2

#: The phases after the fit (``report.json``'s ``seconds_parts``), whose sum issue 26 bounds by half the fit's.
POST_FIT = ("topology", "validity", "refine", "edge_slivers")


def table(header, rows):
    """A Markdown table (header, separator and rows), as text."""
    rows = [[str(c) for c in r] for r in rows]
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


def run_tree(cmd, poll=POLL_SECONDS, timeout=None):
    """Run ``cmd``; its wall seconds, CPU seconds and the peak RSS (MiB) summed over it and its descendants.

    The CPU time is the child's own ``os.wait4`` usage (its descendants' once they are waited for); the memory
    is polled with psutil every ``poll`` seconds over the child and every descendant process alive then.

    Raises
    ------
    subprocess.CalledProcessError
        If the command fails; ``subprocess.TimeoutExpired`` past ``timeout`` seconds (the tree is killed).
    """
    import psutil

    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL)
    top, peak = psutil.Process(proc.pid), 0
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            break
        total = 0
        try:
            for p in [top, *top.children(recursive=True)]:
                try:
                    total += p.memory_info().rss
                except psutil.Error:
                    pass
        except psutil.Error:
            pass
        peak = max(peak, total)
        if timeout is not None and time.perf_counter() - t0 > timeout:
            for p in [*top.children(recursive=True), top]:
                try:
                    p.kill()
                except psutil.Error:
                    pass
            os.waitpid(proc.pid, 0)
            raise subprocess.TimeoutExpired(cmd, timeout)
        time.sleep(poll)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise subprocess.CalledProcessError(proc.returncode, cmd)
    return wall, usage.ru_utime + usage.ru_stime, peak / 2**20


def simulate_case(folder, n, *, seed=0, det_count=None, angles=None):
    """The column simulation folder of case ``n`` in ``folder``, made unless it holds one.

    An existing column simulation is reused when its seed, and the detector columns and projections given
    (None: any), match; another one is refused.

    Returns
    -------
    (Path, float or None)
        The folder and the seconds the simulation took (None when reused).
    """
    folder = Path(folder)
    meta_path = folder / "phantom.json"
    if meta_path.is_file():
        meta = json.loads(meta_path.read_text())
        c = meta.get("column", {})
        if meta.get("phantom") == "column" and meta.get("seed") == seed and angles in (None, meta.get("angles")) \
                and det_count in (None, c.get("cols")):
            return folder, None
        raise ValueError(f"{folder} holds another simulation ({meta.get('phantom')}, seed {meta.get('seed')}, "
                         f"{meta.get('angles')} angles, {c.get('cols')} columns); choose another folder")
    t0 = time.perf_counter()
    subprocess.run(_cli("simulate", "--phantom", "column", "--bubbles", n, "--seed", seed, "--det-count",
                        det_count or 768, "--angles", angles or 40, "--out", folder), check=True,
                   stdout=subprocess.DEVNULL)
    return folder, time.perf_counter() - t0


def score_case(rec_dir, sim_dir):
    """DDI (``bubsub evaluate``) and the matching scores of :func:`bubsub.bench.matching.match`."""
    meta, tab = column_truth(sim_dir)
    scores = match(truth_labels(meta, tab), mesh_labels(read_ply(Path(rec_dir) / "bubbles.ply"), meta),
                   cut=(tab["cut_top"] > 0) | (tab["cut_bottom"] > 0))
    scores["ddi_evaluate"] = evaluate_dir(rec_dir, sim_dir)["ddi"]
    return scores


def _units(report, rows, cols, n_angles):
    """The measured slabs: ``(seconds, core rows, read rows, bubbles)`` each; the whole run when there are none."""
    slabs = report.get("slabs") or []
    units = [(s.get("seconds_total"), s["core_rows"][1] - s["core_rows"][0], s["read_rows"][1] - s["read_rows"][0],
              s.get("bubbles")) for s in slabs if s.get("seconds_total") and s.get("bubbles")]
    if not units:
        units = [(report["seconds_total"], rows, rows, report["bubbles"])]
    return units


def project(report, shape, bubbles, tomo=TOMO_00080, tomo_bubbles=None, workers=(1, 16), halo_rows=None):
    """Projected wall seconds of one tomo_00080 subscan from a run's slabs (see the module docstring).

    Parameters
    ----------
    report : dict
        The run's ``report.json``.
    shape : (n_angles, rows, cols)
        The measured scan.
    bubbles : int
        Truth bubbles of the measured column (for the bubble density).
    tomo : (n_angles, rows, cols)
    tomo_bubbles : int, optional
        Bubbles in the subscan (default: the column's bubbles per ``rows x cols^2`` pixel volume, unbinned).
    workers : tuple of int
    halo_rows : float, optional
        Halo rows of the measured column for a run without slabs (a whole run has none, but the subscan's
        slabs read them; default 0).

    Returns
    -------
    list of dict
        One per binning (1, 2): slabs, bubbles, and ``{model: {workers: seconds}}``.
    """
    n_angles, rows, cols = shape
    units = _units(report, rows, cols, n_angles)
    per_pb = np.median([t / (n_angles * read * cols * b) for t, _, read, b in units])
    per_p = np.median([t / (n_angles * read * cols) for t, _, read, _ in units])
    core = float(np.median([c for _, c, _, _ in units]))
    halo = float(np.median([(r - c) / 2 for _, c, r, _ in units])) if report.get("slabs") else float(halo_rows or 0)
    t_angles, t_rows, t_cols = tomo
    b_tomo = tomo_bubbles or bubbles * (t_rows * t_cols**2) / (rows * cols**2)
    out = []
    for binning in (1, 2):
        r, c = t_rows // binning, t_cols // binning
        core_t, halo_t = max(1.0, core / binning), halo / binning
        n_slabs = math.ceil(r / core_t)
        read = min(r, core_t + 2 * halo_t)
        pixels = t_angles * read * c
        b_slab = b_tomo * read / r
        slab = {"pixels x bubbles": per_pb * pixels * b_slab, "pixels": per_p * pixels}
        out.append({"binning": binning, "shape": (t_angles, r, c), "slabs": n_slabs, "bubbles": b_tomo,
                    "slab_rows": core_t, "seconds": {m: {w: math.ceil(n_slabs / w) * s for w in workers}
                                                     for m, s in slab.items()}})
    return out


def truth_halo(sim_dir):
    """Halo rows the slabs of a simulated column would read: the rule of
    :func:`bubsub.clients.pipeline.regions.slabs.estimate_halo` on the 95th percentile of its true bubbles' radii."""
    meta = json.loads((Path(sim_dir) / "phantom.json").read_text())
    table = np.genfromtxt(Path(sim_dir) / "truth.csv", delimiter=",", names=True)
    radius = 0.5 * float(np.percentile(np.atleast_1d(table["equivalent_diameter_mm"]), 95))
    return halo_rows(radius, meta["column"]["pixel_size_mm"])


def _hours(s):
    return f"{s / 3600:.1f} h" if s >= 3600 else f"{s / 60:.1f} min"


def _run_case(n, args, extra):
    sim, sim_seconds = simulate_case(Path(args.data) / (f"column{n}" if args.det_count == 768 and args.angles == 40
                                                        else f"column{n}_{args.det_count}x{args.angles}"), n,
                                     seed=args.seed, det_count=args.det_count, angles=args.angles)
    runs = []
    for k in range(args.repeats):
        rec = Path(args.out) / f"column{n}_run{k}"
        wall, cpu, rss = run_tree(_cli("reconstruct", sim / "scan.h5", "--out", rec, "--quiet", "--overwrite",
                                       *extra), timeout=args.timeout)
        report = json.loads((rec / "report.json").read_text())
        runs.append({"wall": wall, "cpu": cpu, "rss": rss, "report": report, **score_case(rec, sim)})
    return sim, sim_seconds, runs


_CASE_HEADER = ["run", "wall s", "CPU s", "peak RSS MiB"]
_SCORE_KEYS = ("truth", "found", "missed", "merged", "spurious", "cut_truth", "cut_found", "cut_merged")


def _case_rows(runs, phases):
    rows = []
    for k, r in enumerate(runs + [None]):
        if r is None:
            if len(runs) == 1:
                break
            med = {key: float(np.median([x[key] for x in runs])) for key in ("wall", "cpu", "rss", "ddi_evaluate",
                                                                              "ddi", *_SCORE_KEYS)}
            med["report"] = {"seconds_parts": {p: float(np.median([x["report"].get("seconds_parts", {}).get(p, 0)
                                                                   for x in runs])) for p in phases}}
            r, name = med, "median"
        else:
            name = str(k)
        parts = r["report"].get("seconds_parts", {})
        rows.append([name, f"{r['wall']:.0f}", f"{r['cpu']:.0f}", f"{r['rss']:.0f}"]
                    + [f"{parts.get(p, 0):.0f}" for p in phases]
                    + [f"{r['ddi_evaluate']:.4f}", f"{r['ddi']:.4f}"] + [f"{r[s]:.0f}" for s in _SCORE_KEYS])
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(prog="bubsub bench scale", description=__doc__.split("\n\n")[0],
                                 epilog="Unknown options go to bubsub reconstruct (e.g. --workers 2).")
    default = ",".join(map(str, COLUMN_PRESETS))
    ap.add_argument("--cases", default=default, help=f"bubble counts, comma separated (default {default})")
    ap.add_argument("--repeats", type=int, default=1, help="reconstructions per case (default 1; medians printed)")
    ap.add_argument("--data", default=None, help="folder of the simulations, reused when present (default OUT/sims)")
    ap.add_argument("--out", default="bench-scale", help="folder of the reconstructions and scale.json")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--det-count", type=int, default=768, help="detector columns (rows: a third); default 768")
    ap.add_argument("--angles", type=int, default=40)
    ap.add_argument("--tomo-bubbles", type=int, help="bubbles in a tomo_00080 subscan (default: scaled by volume)")
    ap.add_argument("--timeout", type=float, help="seconds allowed per reconstruction")
    args, extra = ap.parse_known_args(argv)
    try:
        cases = [int(c) for c in args.cases.split(",") if c.strip()]
    except ValueError:
        ap.error(f"--cases must be comma-separated integers, got {args.cases!r}")
    if not cases or min(cases) < 1 or args.repeats < 1:
        ap.error("need at least one positive case and --repeats >= 1")
    args.data = args.data or str(Path(args.out) / "sims")
    Path(args.out).mkdir(parents=True, exist_ok=True)
    results = {}
    for n in cases:
        sim, sim_seconds, runs = _run_case(n, args, extra)
        results[n] = (sim, sim_seconds, runs)
        _print_case(n, sim, sim_seconds, runs, args, extra)
    _print_growth(results)
    _print_projection(results, args)
    doc = {str(n): {"simulation": str(sim), "simulation_seconds": s,
                    "runs": [{k: v for k, v in r.items() if k != "per_truth"} for r in runs]}
           for n, (sim, s, runs) in results.items()}
    (Path(args.out) / "scale.json").write_text(json.dumps({"reconstruct_options": extra, "cases": doc}, indent=1,
                                                          default=str))
    return 0


def _phases(runs):
    seen = [p for p in PHASES if any(p in r["report"].get("seconds_parts", {}) for r in runs)]
    return seen + sorted({p for r in runs for p in r["report"].get("seconds_parts", {})} - set(seen))


def _print_case(n, sim, sim_seconds, runs, args, extra):
    meta = json.loads((sim / "phantom.json").read_text())
    c = meta["column"]
    made = "reused" if sim_seconds is None else f"simulated in {sim_seconds:.0f} s"
    print(f"\n## column ~{n}: {meta['bubbles']} bubbles in the field of view ({c['bubbles_cut_top']} cut by the top, "
          f"{c['bubbles_cut_bottom']} by the bottom row), gas fraction {c['gas_fraction_in_fov']:.3f}, "
          f"{meta['angles']} x {c['rows']} x {c['cols']}; {sim} ({made}); bubsub reconstruct "
          f"{' '.join(extra) or '(defaults)'}\n")
    phases = _phases(runs)
    header = _CASE_HEADER + [f"{p.replace('_', ' ')} s" for p in phases] + [
        "DDI (evaluate)", "DDI in FOV", "truth", "found", "missed", "merged", "spurious", "cut", "cut found",
        "cut merged"]
    print(table(header, _case_rows(runs, phases)), flush=True)


def _median(runs, key):
    return float(np.median([r[key] for r in runs]))


def _post_fit(run):
    parts = run["report"].get("seconds_parts", {})
    fit = parts.get("fit", 0.0)
    post = sum(parts.get(p, 0.0) for p in POST_FIT)
    return post / fit if fit else float("nan")


def _print_growth(results):
    ns = sorted(results)
    print("\n## growth with the bubble count (medians)\n")
    rows = []
    for a, b in zip(ns, ns[1:]):
        ra, rb = results[a][2], results[b][2]
        ta, tb = _median(ra, "wall"), _median(rb, "wall")
        ba, bb = _median(ra, "truth"), _median(rb, "truth")
        rows.append([f"{a} -> {b}", f"{bb / ba:.2f}", f"{tb / ta:.2f}", f"{math.log(tb / ta) / math.log(bb / ba):.2f}",
                     f"{_median(rb, 'rss') / _median(ra, 'rss'):.2f}"])
    rows += [[f"{n}: post-fit / fit", "", "", "", f"{np.median([_post_fit(r) for r in results[n][2]]):.2f}"]
             for n in ns]
    print(table(["cases", "bubbles ratio", "wall ratio", "exponent (wall ~ bubbles^k)", "peak RSS ratio"], rows))
    print("\npost-fit / fit: topology + validity + refine + edge slivers seconds over the fit's "
          "(issue 26's target: <= 0.5)")


def _print_projection(results, args):
    print("\n## projection to one tomo_00080 subscan (300 projections of 1800 x 2016, and 2x binned)\n")
    rows = []
    for n, (sim, _, runs) in sorted(results.items()):
        meta = json.loads((sim / "phantom.json").read_text())
        shape = (meta["angles"], meta["column"]["rows"], meta["column"]["cols"])
        median = sorted(runs, key=lambda r: r["wall"])[len(runs) // 2]
        measured = "slabs" if median["report"].get("slabs") else "whole run"
        for p in project(median["report"], shape, meta["bubbles"], tomo_bubbles=args.tomo_bubbles,
                         halo_rows=truth_halo(sim)):
            for model, secs in p["seconds"].items():
                rows.append([f"~{n} ({measured})", f"{p['binning']}x", " x ".join(map(str, p["shape"])),
                             f"{p['bubbles']:.0f}", f"{p['slabs']} of {p['slab_rows']:.0f} rows", model,
                             _hours(secs[1]), _hours(secs[16])])
    print(table(["from case", "binning", "subscan", "bubbles", "slabs", "cost model", "1 worker", "16 workers"], rows))
    print("\ncost model 'pixels x bubbles': each slab costs the measured seconds per slab pixel and bubble; 'pixels': "
          "the measured seconds per slab pixel (work local to each bubble's footprint). A run without "
          "report.json 'slabs' is one slab of all its rows; the subscan's slabs of as many rows read the halo "
          "of the column's bubbles (truth_halo) as well.")


if __name__ == "__main__":
    sys.exit(main())
