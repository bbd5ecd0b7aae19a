"""``bubsub bench dynamic``: ``bubsub reconstruct4d`` on a flowing, coarsening foam per subscan, beside a voxel route.

The scan is ``bubsub simulate --phantom flowing3d`` (:mod:`bubsub.core.foam.flowing`:
by default 12 subscans of 40 parallel projections over 180 degrees, continuous
rotation, 128 x 384 pixels of 12 um, ~150 polydisperse ellipsoidal bubbles in
view flowing up 4 pixels per subscan, the smallest 12 % shrinking to nothing,
4 coalescences, the foam moving between projections, Poisson noise at
I0 = 1e4), made in ``DATA`` unless a simulation with the same settings is
there. Two routes run on it, each in a child process whose wall time and peak
RSS summed over its process tree are measured (:func:`bubsub.bench.scale.run_tree`):

* ``bubsub reconstruct4d`` with its defaults (options this benchmark does not
  know are passed on to it);
* the **voxel route**: per subscan, SIRT (``--sirt-iterations``, default 100)
  of the subscan's projections on the evaluation grid coarsened ``--voxel-bin``
  times, Otsu inside the liquid cylinder, a distance watershed
  (:func:`bubsub.bench.fov.voxel_route`), its labels repeated back onto the
  evaluation grid; ids linked forward in time by overlap (a label continues the
  previous subscan's label it overlaps most when each is the other's best
  match and they share at least 30 % of the later label's voxels).

Each subscan is scored against the truth at its mid-time inside the field of view
(:mod:`bubsub.bench.dynamic_scores`: true, found, merged, missed, spurious, DDI, the bubbles found anew, the
small ones, and track purity).

``python -m bubsub.bench dynamic [--data DIR] [--out DIR] [--seed 0] [--bubbles 150] [--det-count 384]
[--subscans 12] [--projections-per-subscan 40] [--flow 4] [--vanishing 0.12] [--coalescences 4]
[--sirt-iterations 100] [--voxel-bin 1] [--no-voxel] [--reuse-voxel]
[--no-bubsub] [--rec DIR] [--order backward|forward] [RECONSTRUCT4D OPTIONS]``

``--order forward`` runs ``reconstruct4d`` on the scan with its subscans in
reverse order (:func:`reversed_scan`), so that its chain runs forwards in the
foam's time; its subscans are scored as the simulation's. Before any route, the
truth alone says how many bubbles each order must find anew and why
(:func:`~bubsub.bench.dynamic_scores.chain_burden`).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from bubsub.bench.dynamic_scores import SMALL_BALL, chain_burden, flowing_truth, read_lineage, score_run
from bubsub.bench.matching import mesh_labels, overlaps
from bubsub.bench.fov import voxel_route
from bubsub.bench.reconstruct import cli_command
from bubsub.bench.scale import run_tree, table
from bubsub.clients.pipeline.inputs.fov import fov_mask
from bubsub.core.foam.flowing import FLOWING_DEFAULTS as D
from bubsub.core.io.meshio import read_ply
from bubsub.core.io.scanfile import read_scan, write_scan
from bubsub.core.io.subscans import subscan, subscan_layout

__all__ = ["LINK_SHARE", "link_by_overlap", "bubsub_labels", "voxel_labels", "run_voxel_route", "reversed_scan",
           "simulate_flowing_case", "format_table", "coalescence_cell", "main"]

#: Shared share of the later label's voxels that links two voxel-route labels.
LINK_SHARE = 0.3


def link_by_overlap(previous, previous_ids, labels, next_id, share=LINK_SHARE):
    """Track ids of a label image linked to the previous subscan's labels by overlap.

    Parameters
    ----------
    previous : int ndarray or None
        The previous subscan's labels ``1..m`` (None: none).
    previous_ids : (m,) int
        Their track ids.
    labels : int ndarray
        This subscan's labels ``1..n``.
    next_id : int
        First unused track id.
    share : float
        Least shared fraction of the later label's voxels.

    Returns
    -------
    ids : (n,) int
    next_id : int
    """
    n = int(labels.max(initial=0))
    ids = np.full(n, -1, dtype=np.int64)
    if previous is not None and n and previous.max(initial=0):
        table, _, n_now = overlaps(previous, labels)
        t = table[1:, 1:n + 1]
        best_prev = np.argmax(t, axis=0)
        best_next = np.argmax(t, axis=1)
        for j in range(n):
            i = best_prev[j]
            if t[i, j] > 0 and best_next[i] == j and t[i, j] >= share * n_now[j + 1]:
                ids[j] = previous_ids[i]
    for j in np.flatnonzero(ids < 0):
        ids[j] = next_id
        next_id += 1
    return ids, next_id


def bubsub_labels(rec_dir, meta):
    """``k -> (labels, track ids)`` of a ``bubsub reconstruct4d`` folder (None for a subscan it lacks)."""
    rec_dir = Path(rec_dir)

    def labels_of(k):
        path = rec_dir / f"subscan_{k:04d}" / "bubbles.ply"
        if not path.is_file():
            return None
        meshes, ids = read_ply(path, with_ids=True)
        return mesh_labels(meshes, meta), np.asarray(ids, dtype=np.int64)

    return labels_of


def voxel_labels(path):
    """``k -> (labels, track ids)`` of the voxel route's ``labels.npz`` (:func:`run_voxel_route`)."""
    data = np.load(path)

    def labels_of(k):
        if f"labels_{k}" not in data:
            return None
        return data[f"labels_{k}"], data[f"ids_{k}"]

    return labels_of


def run_voxel_route(sim_dir, out, *, iterations=100, voxel_bin=1):
    """The voxel route on every subscan, tracked by overlap, into ``out/labels.npz``; per subscan seconds.

    Parameters
    ----------
    sim_dir : path
        A flowing foam's simulation folder.
    out : path
        Folder (created); ``labels.npz`` holds ``labels_k`` (int32 on the evaluation grid, 0 outside the field
        of view) and ``ids_k`` per subscan, ``seconds.json`` the seconds per subscan.
    iterations : int
        SIRT iterations.
    voxel_bin : int
        The SIRT grid's voxel is this many evaluation-grid voxels.
    """
    sim_dir, out = Path(sim_dir), Path(out)
    out.mkdir(parents=True, exist_ok=True)
    meta = json.loads((sim_dir / "phantom.json").read_text())
    scan = read_scan(sim_dir / "scan.h5")
    layout = subscan_layout(scan)
    shape, extent = tuple(meta["grid_shape"]), tuple(meta["grid_extent"])
    b = int(voxel_bin)
    if b < 1:
        raise ValueError(f"--voxel-bin must be a positive integer, got {voxel_bin}")
    coarse = tuple(int(np.ceil(s / b)) for s in shape)
    # the coarse grid starts where the evaluation grid does (x min, y max: row 0, z min) and runs past its
    # far ends, so that each coarse voxel holds b x b x b evaluation voxels
    ext = list(extent)
    for axis, (n, nc) in enumerate(zip(shape[::-1], coarse[::-1])):
        step = (extent[2 * axis + 1] - extent[2 * axis]) / n
        if axis == 1:
            ext[2] = extent[3] - nc * b * step
        else:
            ext[2 * axis + 1] = extent[2 * axis] + nc * b * step
    inside = fov_mask(shape, extent, (meta["column"]["fov_radius_mm"], meta["column"]["fov_half_height_mm"]))
    result, seconds, previous, prev_ids, next_id = {}, [], None, None, 0
    for k in layout.selected:
        t0 = time.perf_counter()
        lab = voxel_route(subscan(scan, layout, k), dict(meta, grid_shape=list(coarse), grid_extent=ext), iterations)
        if b > 1:
            lab = np.repeat(np.repeat(np.repeat(lab, b, 0), b, 1), b, 2)[:shape[0], :shape[1], :shape[2]]
        lab = np.where(inside, lab, 0)
        kept, lab = np.unique(lab, return_inverse=True)
        lab = lab.reshape(shape).astype(np.int32)
        if kept[0] != 0:
            lab += 1
        ids, next_id = link_by_overlap(previous, prev_ids, lab, next_id)
        result[f"labels_{k}"], result[f"ids_{k}"] = lab, ids
        previous, prev_ids = lab, ids
        seconds.append(time.perf_counter() - t0)
        print(f"voxel route: subscan {k}, {int(lab.max())} labels, {seconds[-1]:.0f} s", file=sys.stderr, flush=True)
    np.savez_compressed(out / "labels.npz", **result)
    (out / "seconds.json").write_text(json.dumps({"seconds": seconds, "iterations": iterations,
                                                  "voxel_bin": b, "grid_shape": list(coarse)}))
    return out / "labels.npz"


def reversed_scan(sim_dir, path):
    """The simulation's scan with its subscans in reverse order (each subscan's projections kept in order).

    ``bubsub reconstruct4d`` goes backwards in time; on this scan its chain runs
    forwards in the simulation's time. Subscan ``k`` of the file is the
    simulation's subscan ``n - 1 - k``; ``/exchange/time`` runs on in the new order.

    Returns
    -------
    Path
    """
    scan = read_scan(Path(sim_dir) / "scan.h5")
    layout = subscan_layout(scan)
    order = np.concatenate([np.arange(scan.n_angles)[layout.projections(k)] for k in reversed(layout.selected)])
    out = scan.subset(order)
    step = float(np.median(np.diff(scan.time))) if scan.time is not None and scan.n_angles > 1 else 1.0
    out.time = np.arange(len(order)) * step
    out.projections_per_subscan = layout.per_subscan
    out.attrs["subscans_reversed"] = 1
    return write_scan(path, out)


def simulate_flowing_case(folder, *, seed=0, bubbles=None, det_count=None, subscans=None, per_subscan=None,
                          **foam):
    """The flowing foam's simulation folder, made unless it holds one with these settings.

    ``foam``: ``flow``, ``vanishing``, ``coalescences`` of ``bubsub simulate`` (None: its default).

    Returns
    -------
    (Path, float or None)
        The folder and the seconds the simulation took (None when reused).
    """
    folder = Path(folder)
    want = {"seed": seed, "cols": det_count or D["cols"], "subscans": subscans or D["subscans"],
            "projections_per_subscan": per_subscan or D["projections_per_subscan"],
            "bubbles_asked": bubbles or D["n_bubbles"],
            **{k: v for k, v in foam.items() if v is not None}}
    key = folder / "bench_key.json"
    if key.is_file() and json.loads(key.read_text()) == want and (folder / "scan.h5").is_file():
        return folder, None
    t0 = time.perf_counter()
    subprocess.run(cli_command("simulate", "--phantom", "flowing3d", "--seed", seed, "--bubbles",
                               want["bubbles_asked"], "--det-count", want["cols"], "--subscans", want["subscans"],
                               "--projections-per-subscan", want["projections_per_subscan"], "--out", folder,
                               "--overwrite", *[x for k, v in foam.items() if v is not None for x in (f"--{k}", v)]),
                   check=True, stdout=subprocess.DEVNULL)
    key.write_text(json.dumps(want))
    return folder, time.perf_counter() - t0


def _fmt(x, nd=4):
    return "" if x is None else (f"{x:.{nd}f}" if isinstance(x, float) else str(x))


def format_table(name, scores, seconds=None):
    """A Markdown table of one route's per-subscan scores and its totals row.

    ``seconds``: per subscan ``(start, seconds)`` (e.g. from ``report.json``), or None.
    """
    header = ["subscan", "start", "s", "true", "found", "missed", "merged", "spurious", "DDI", "anew found/all",
              "anew >= 6 px found/all", "small found/all"]
    body = []
    for p in scores["subscans"]:
        start, sec = (seconds or {}).get(p["subscan"], ("", None))
        body.append([p["subscan"], start, _fmt(sec, 0), p["truth"], p["found"], p["missed"], p["merged"],
                     p["spurious"], _fmt(p["ddi"]), f"{p['anew_found']}/{p['anew']}",
                     f"{p['anew6_found']}/{p['anew6']}", f"{p['small_found']}/{p['small']}"])
    t = scores["totals"]
    total_s = sum(s for _, s in (seconds or {}).values() if s is not None) if seconds else None
    share = f"{t['found']} ({100 * (t['found_share'] or 0):.1f} %)"
    body.append([f"**{name}**", "", _fmt(total_s, 0), t["truth"], share,
                 t["missed"], t["merged"], t["spurious"], f"{_fmt(t['mean_ddi'])} (mean)",
                 f"{t['anew_found']}/{t['anew']}", f"{t['anew6_found']}/{t['anew6']}",
                 f"{t['small_found']}/{t['small']}"])
    return table(header, body)


def coalescence_cell(c):
    """``two before / one after / in the lineage, of N; false rows of all rows`` of
    :func:`~bubsub.bench.dynamic_scores.score_coalescences` (``-`` where the route keeps no lineage), with the
    rows a subscan off in brackets where there are any."""
    lin = "-" if c["in_lineage"] is None else str(c["in_lineage"])
    false = "-" if c["false_rows"] is None else f"{c['false_rows']} of {c['rows']}"
    if c.get("in_lineage_a_subscan_off"):
        lin += f" (+{c['in_lineage_a_subscan_off']} a subscan off)"
    if c.get("false_rows_a_subscan_off"):
        false += f" ({c['false_rows_a_subscan_off']} a true one a subscan off)"
    return f"{c['two_before']} / {c['one_after']} / {lin}, of {c['events']}; {false}"


def _bubsub_seconds(rec_dir):
    """``{subscan: (start, seconds)}`` from each subscan folder's ``report.json`` (empty where there is none)."""
    out = {}
    for path in sorted(Path(rec_dir).glob("subscan_*/report.json")):
        p = json.loads(path.read_text())
        if "subscan" in p:
            out[int(p["subscan"])] = (p.get("start", ""), p.get("seconds"))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m bubsub.bench dynamic", description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="bench-dynamic/flowing3d", help="simulation folder (made when missing)")
    ap.add_argument("--out", default="bench-dynamic", help="folder of the routes' outputs (default bench-dynamic)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--bubbles", type=int, help="about this many bubbles in view (default 150)")
    ap.add_argument("--det-count", type=int, help="detector columns, a third as many rows (default 384)")
    ap.add_argument("--subscans", type=int, help="default 12")
    ap.add_argument("--projections-per-subscan", type=int, help="default 40")
    ap.add_argument("--flow", type=float, help="pixels per subscan (default 4)")
    ap.add_argument("--vanishing", type=float, help="share of the bubbles that vanish (default 0.12)")
    ap.add_argument("--coalescences", type=int, help="default 4")
    ap.add_argument("--sirt-iterations", type=int, default=100, help="the voxel route's SIRT iterations (100)")
    ap.add_argument("--voxel-bin", type=int, default=1,
                    help="the voxel route's grid voxel in evaluation-grid voxels (two pixels each; default 1)")
    ap.add_argument("--no-voxel", action="store_true", help="skip the voxel route")
    ap.add_argument("--no-bubsub", action="store_true", help="skip bubsub reconstruct4d")
    ap.add_argument("--reuse-voxel", action="store_true",
                    help="reuse the voxel route's labels and measured cost in OUT/voxel when made with the same "
                         "simulation and settings")
    ap.add_argument("--rec", help="score this reconstruct4d folder instead of running one")
    ap.add_argument("--order", choices=("backward", "forward"), default="backward",
                    help="forward: run reconstruct4d on the scan with its subscans reversed, so that its chain runs "
                         "forwards in time (default backward, as reconstruct4d)")
    ap.add_argument("--json", help="also write all scores to this JSON file")
    ap.add_argument("--voxel-child", nargs=2, metavar=("SIM", "OUT"), help=argparse.SUPPRESS)
    args, extra = ap.parse_known_args(argv)
    if args.voxel_child:
        run_voxel_route(*args.voxel_child, iterations=args.sirt_iterations, voxel_bin=args.voxel_bin)
        return 0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sim, sim_s = simulate_flowing_case(Path(args.data), seed=args.seed, bubbles=args.bubbles,
                                       det_count=args.det_count, subscans=args.subscans,
                                       per_subscan=args.projections_per_subscan, flow=args.flow,
                                       vanishing=args.vanishing, coalescences=args.coalescences)
    meta, tables, events = flowing_truth(sim)
    f = meta["flowing"]
    vanishing = sum(e["event"] == "vanish" and e["in_fov"] == "1" for e in events)
    print(f"flowing foam {sim}: {meta['subscans']} subscans of {meta['projections_per_subscan']} x "
          f"{meta['column']['rows']} x {meta['column']['cols']}, {min(f['bubbles_per_subscan'])}-"
          f"{max(f['bubbles_per_subscan'])} bubbles in view, {meta['bubbles']} over the run, flow "
          f"{f['flow_px_per_subscan']:g} px per subscan, {vanishing} vanishing in view, "
          f"{len(f['coalescences'])} coalescences"
          + (f" (simulated in {sim_s:.0f} s)" if sim_s else " (reused)") + "\n", flush=True)
    burden = chain_burden(meta, tables, events)
    for d, b in burden.items():
        reasons = ", ".join(f"{n} {r}" for r, n in sorted(b["reasons"].items(), key=lambda x: -x[1]))
        print(f"a {d} chain must find {b['all']} bubbles anew ({reasons}); {b['ball6']} of them show a ball of "
              f"at least {SMALL_BALL[0]:g} px in view")
    print(flush=True)
    results = {}
    if not args.no_bubsub:
        forward = args.order == "forward"
        if args.rec:
            rec = Path(args.rec)
            cost = out / f"{rec.name}_cost.json"  # what the run that made it measured, when this bench made it
            wall, rss = (json.loads(cost.read_text())[k] for k in ("wall_s", "peak_rss_mib")) if cost.is_file() \
                else (None, None)
        else:
            rec = out / ("bubsub-forward" if forward else "bubsub")
            scan_file = reversed_scan(sim, out / "scan_reversed.h5") if forward else sim / "scan.h5"
            wall, _, rss = run_tree(cli_command("reconstruct4d", scan_file, "--out", rec, "--quiet",
                                                "--overwrite", *extra))
            (out / f"{rec.name}_cost.json").write_text(json.dumps({"wall_s": wall, "peak_rss_mib": rss,
                                                                   "options": extra}))
        last = meta["subscans"] - 1
        labels = bubsub_labels(rec, meta)
        secs = _bubsub_seconds(rec)
        if forward:
            labels_fwd = labels
            labels = lambda k: labels_fwd(last - k)  # noqa: E731
            secs = {last - k: v for k, v in secs.items()}
        scores = score_run(meta, tables, labels, events=events, lineage=None if forward else read_lineage(rec))
        cold = [s for st, s in secs.values() if st == "cold"]
        warm = [s for st, s in secs.values() if st == "warm"]
        name = (f"bubsub reconstruct4d (from {rec})" if args.rec
                else "bubsub reconstruct4d " + (" ".join(extra) or "(defaults)")) + (", forwards" if forward else "")
        results["bubsub"] = {"route": name, **scores, "wall_s": wall, "peak_rss_mib": rss,
                             "seconds_cold": float(sum(cold)) if cold else None,
                             "seconds_warm_median": float(np.median(warm)) if warm else None,
                             "cold_ddi": next((p["ddi"] for p in scores["subscans"]
                                               if secs.get(p["subscan"], ("",))[0] == "cold"), None)}
        print(f"### {name}\n\n{format_table('all', scores, secs)}\n", flush=True)
    if not args.no_voxel:
        vox = out / "voxel"
        want = {"simulation": json.loads((sim / "bench_key.json").read_text()), "iterations": args.sirt_iterations,
                "voxel_bin": args.voxel_bin}
        done = vox / "route.json"
        if args.reuse_voxel and done.is_file() and json.loads(done.read_text())["settings"] == want:
            wall, rss = (json.loads(done.read_text())[k] for k in ("wall_s", "peak_rss_mib"))
        else:
            done.unlink(missing_ok=True)
            wall, _, rss = run_tree(cli_command("bench", "dynamic", "--voxel-child", sim, vox, "--sirt-iterations",
                                                args.sirt_iterations, "--voxel-bin", args.voxel_bin))
            done.write_text(json.dumps({"settings": want, "wall_s": wall, "peak_rss_mib": rss}))
        scores = score_run(meta, tables, voxel_labels(vox / "labels.npz"), events=events)
        sec = json.loads((vox / "seconds.json").read_text())
        secs = {k: ("", s) for k, s in enumerate(sec["seconds"])}
        name = (f"voxel route: SIRT {args.sirt_iterations} on {' x '.join(map(str, sec['grid_shape']))} voxels "
                f"+ Otsu + distance watershed, tracked by overlap")
        results["voxel"] = {"route": name, **scores, "wall_s": wall, "peak_rss_mib": rss, "seconds": sec["seconds"]}
        print(f"### {name}\n\n{format_table('all', scores, secs)}\n", flush=True)
    _print_summary(results)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=float))
    return 0


def _print_summary(results):
    if not results:
        return
    cols = list(results)
    t = {k: results[k]["totals"] for k in cols}

    def row(label, fn):
        return [label] + [fn(k) for k in cols]

    def worst(k):
        return min((p["found"] / p["truth"] for p in results[k]["subscans"] if p["truth"]), default=0.0)

    def pct(a, b):
        return f"{a}/{b} ({100 * a / b:.1f} %)" if b else "0/0"

    body = [
        row("true bubbles found, all subscans", lambda k: pct(t[k]["found"], t[k]["truth"])),
        row("true bubbles found, visible part holding a ball >= 6 px", lambda k: pct(t[k]["found6"], t[k]["truth6"])),
        row("merged (true bubbles)", lambda k: str(t[k]["merged"])),
        row("spurious", lambda k: str(t[k]["spurious"])),
        row("worst subscan found", lambda k: f"{worst(k) * 100:.1f} %"),
        row("bubbles found anew (all)", lambda k: pct(t[k]["anew_found"], t[k]["anew"])),
        row("bubbles found anew (ball >= 6 px)", lambda k: pct(t[k]["anew6_found"], t[k]["anew6"])),
        row("bubbles a forward chain would find anew, found here (all; ball >= 6 px)",
            lambda k: f"{pct(t[k]['fwd_found'], t[k]['fwd'])}; {pct(t[k]['fwd6_found'], t[k]['fwd6'])}"),
        row("small bubbles found (ball 6-12 px)", lambda k: pct(t[k]["small_found"], t[k]["small"])),
        row("coalescences: two before / one after / in the lineage, of N; false rows",
            lambda k: coalescence_cell(t[k]["coalescences"])),
        row("mean DDI in the FOV", lambda k: _fmt(t[k]["mean_ddi"])),
        row("cold subscan DDI", lambda k: _fmt(results[k].get("cold_ddi"))),
        row("track purity (tracks, rows)",
            lambda k: f"{_fmt(t[k]['track_purity'], 3)} ({t[k]['tracks']}, {t[k]['rows']})"),
        row("seconds: cold subscan / median warm", lambda k: f"{_fmt(results[k].get('seconds_cold'), 0)} / "
            f"{_fmt(results[k].get('seconds_warm_median'), 0)}" if k == "bubsub" else
            f"{_fmt(float(np.median(results[k]['seconds'])), 0)} per subscan"),
        row("wall s, peak RSS MiB (process tree)", lambda k: f"{_fmt(results[k]['wall_s'], 0)}, "
            f"{_fmt(results[k]['peak_rss_mib'], 0)}"),
    ]
    print(table([""] + [results[k]["route"] for k in cols], body), flush=True)


if __name__ == "__main__":
    sys.exit(main())
