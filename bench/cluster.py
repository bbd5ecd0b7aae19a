"""``python -m bubsub.bench cluster``: 4D wall time in-process against an embedded Dask cluster.

On one simulated dynamic scan (2D or 3D expanding foam) it times, side by side
and interleaved over ``--repeats`` rounds:

* in-process with the projector on every core (the default) and on 1 thread,
* ``--workers 2`` (1 thread per worker) with one chain, and with ``--chunks 2``;

then the per-task overhead of the embedded cluster (start-up, round trip of
an empty task, throughput of many), and an estimate for a 130-subscan run
(tomo_00080-sized in subscans) on N workers from the measured cold and warm
per-subscan costs: ``t_cold + ceil(129 / N) * t_warm`` with ``--chunks N``
against ``t_cold + 129 * t_warm`` for one chain. Medians are printed.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from bubsub.bench.reconstruct import cli_command
from bubsub.clients.cluster.engine import local, open_client, run_tasks
from bubsub.clients.pipeline.dynamic4d.chain import DynamicSettings
from bubsub.clients.pipeline.reconstruct4d import reconstruct_dynamic
from bubsub.core.io.scanfile import read_scan


def _simulate(ndim, folder):
    args = (["--phantom", "expanding2d", "--bubbles", "10", "--det-count", "240", "--subscans", "6",
             "--projections-per-subscan", "16"] if ndim == 2 else
            ["--phantom", "expanding3d", "--bubbles", "6", "--det-count", "64", "--subscans", "4",
             "--projections-per-subscan", "16"])
    subprocess.run(cli_command("simulate", *args, "--seed", "5", "--out", folder), check=True,
                   stdout=subprocess.DEVNULL)
    return folder / "scan.h5"


def _run(scan_path, out, client=None, chunks=1, threads=None):
    before = os.environ.get("BUBSUB_THREADS")
    if threads is not None:
        os.environ["BUBSUB_THREADS"] = str(threads)
    try:
        t = time.perf_counter()
        report = reconstruct_dynamic(read_scan(scan_path), out, DynamicSettings(iterations=30, holdout="odd",
                                                                                progress=False),
                                     client=client, chunks=chunks)
        return time.perf_counter() - t, report
    finally:
        if threads is not None:
            os.environ.pop("BUBSUB_THREADS") if before is None else os.environ.__setitem__("BUBSUB_THREADS", before)


def _overhead(client, n=200):
    rt = []
    for _ in range(30):
        t = time.perf_counter()
        client.submit(abs, -1, pure=False).result()
        rt.append(time.perf_counter() - t)
    t = time.perf_counter()
    run_tasks(client, abs, [(-i,) for i in range(n)])
    return statistics.median(rt), (time.perf_counter() - t) / n


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m bubsub.bench cluster", description=__doc__.splitlines()[0])
    ap.add_argument("--ndim", type=int, choices=(2, 3), default=2)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--subscans", type=int, default=130, help="subscans of the estimated run")
    ap.add_argument("--json", help="also write the measurements here")
    args = ap.parse_args(argv)

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        scan = _simulate(args.ndim, tmp / "sim")
        t = time.perf_counter()
        with open_client(local(2)) as client:
            start = time.perf_counter() - t
            warmup = _run(scan, tmp / "warmup", client)[0]  # imports and numba caches on both workers
            configs = {"in-process (all cores)": {}, "in-process (1 thread)": {"threads": 1},
                       "--workers 2": {"client": client}, "--workers 2 --chunks 2": {"client": client, "chunks": 2}}
            times = {k: [] for k in configs}
            reports = {}
            for r in range(args.repeats):
                for name, kw in configs.items():
                    sec, reports[name] = _run(scan, tmp / f"run-{r}-{list(configs).index(name)}", **kw)
                    times[name].append(sec)
            round_trip, per_task = _overhead(client)
    med = {k: statistics.median(v) for k, v in times.items()}
    per = reports["in-process (1 thread)"]["subscans"]
    cold = statistics.median([p["seconds"] for p in per if p["start"] == "cold"])
    warm = statistics.median([p["seconds"] for p in per if p["start"] == "warm"])
    n_sub = len(per)
    base = med["in-process (all cores)"]
    print(f"\n{args.ndim}D expanding foam, {n_sub} subscans, 30 BFGS iterations, {os.cpu_count()} cores, "
          f"median of {args.repeats}; load average at the end {os.getloadavg()[0]:.1f}")
    print("| run | wall s | vs in-process |\n|---|---|---|")
    for k, v in med.items():
        print(f"| {k} | {v:.1f} | {base / v:.2f}x |")
    print(f"\nembedded cluster start (2 workers): {start:.1f} s; first run on it (imports, numba caches): "
          f"{warmup:.1f} s; empty task round trip {1e3 * round_trip:.1f} ms; {1e3 * per_task:.1f} ms per task "
          f"over 200 tasks")
    print(f"per subscan, 1 thread: cold {cold:.2f} s, warm {warm:.2f} s (median)")
    n = args.subscans
    print(f"\nestimate for {n} subscans from these per-subscan costs (cold + warm per chunk; chunks = workers):")
    print("| workers | chunks | estimated wall s | speed-up |\n|---|---|---|---|")
    one = cold + (n - 1) * warm
    for w in (1, 2, 8, 16, 32, 64):
        est = cold + -(-(n - 1) // w) * warm + per_task * (n + w)
        print(f"| {w} | {w} | {est:.0f} | {one / est:.1f}x |")
    if args.json:
        Path(args.json).write_text(json.dumps({"times": times, "cluster_start": start, "round_trip": round_trip,
                                               "per_task": per_task, "cold": cold, "warm": warm}, indent=2))
    return 0
