"""Benchmark "remote": the same BubSub fit run locally and through the projection server.

``python -m bubsub.bench remote [--url URL] [--iterations N] [--repeats R] [--check]``

Two simulated foams (a 2D one and a 3D one, liquid container as the
stationary background) are fitted from the same initial guess with
:func:`bubsub.clients.optimise.fit.fit`, once with a local
:class:`~bubsub.core.MeshProjector` and once with a
:class:`~bubsub.clients.remote.client.RemoteJob` on a server over loopback (started
here in a subprocess, ``python -m bubsub.service``, unless ``--url`` names
one). Prints one table: fit wall times (median of the repeats, local and
remote runs interleaved) and the remote overhead; single objective
evaluations timed in interleaved pairs (median) and their overhead; and the
largest difference between the two fitted control meshes (the remote fit
must follow the local one to round-off). The acceptance target is an overhead
of at most 10 %. Timings need an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass

import numpy as np

from bubsub.clients.remote.client import ProjectorClient
from bubsub.clients.optimise.fit import fit
from bubsub.core import MeshProjector, circle_surface, sphere_surface
from bubsub.core.foam.phantoms import foam2d, foam3d
from bubsub.core.foam.simulate import default_geometry_2d, default_geometry_3d, simulate_2d, simulate_3d

TARGET_OVERHEAD = 0.10


@dataclass
class Case:
    """A fit problem: geometry, measured data and background, initial surfaces."""

    name: str
    geometry: object
    data: np.ndarray
    background: np.ndarray
    init: list

    @property
    def target(self):
        return np.subtract(self.data, self.background, dtype=np.float32)

    @property
    def unknowns(self):
        return sum(s.vertices.size for s in self.init)


def _initial_guess(rng, centres, radii, contrast, make):
    """Bubbles at slightly wrong places with slightly wrong radii."""
    out = []
    for c, r in zip(centres, radii):
        out.append(make(c + rng.normal(scale=0.1 * r, size=len(c)), r * rng.uniform(0.85, 0.95), contrast))
    return out


def case_2d(seed=7):
    """2D as in the paper: 40 bubbles in a 10 mm liquid square, 25 views of 2400 pixels."""
    ph = foam2d(seed, n_bubbles=40)
    g = default_geometry_2d(25)
    scan = simulate_2d(ph, g, method="mesh")
    radii = [b.equivalent_radius for b in ph.bubbles]
    init = _initial_guess(np.random.default_rng(seed), [b.centroid for b in ph.bubbles], radii, ph.contrast,
                          lambda c, r, mu: circle_surface(c, r, mu, control=9))
    return Case("2D foam, 40 bubbles x 9 control pts, 25 x 2400", g, scan.data, scan.background, init)


def case_3d(seed=7):
    """3D: 8 bubbles in a 20 x 20 x 10 mm box, cone beam, 25 views of 128 x 256."""
    ph = foam3d(seed, n_bubbles=8)
    g = default_geometry_3d(25, rows=128, cols=256)
    scan = simulate_3d(ph, g)
    radii = [b.equivalent_radius for b in ph.bubbles]
    init = _initial_guess(np.random.default_rng(seed), [b.centroid for b in ph.bubbles], radii, ph.contrast,
                          lambda c, r, mu: sphere_surface(c, r, mu, control=42))
    return Case("3D foam, 8 bubbles x 42 control pts, 25 x 128 x 256", g, scan.data, scan.background, init)


def _free_port():
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(port, workers=None, blas_threads=None):
    """``python -m bubsub.service`` on 127.0.0.1:port; returns the process."""
    env = {**os.environ, "BUBSUB_LOG_LEVEL": "warning"}
    if workers:
        env["BUBSUB_WORKERS"] = str(workers)
    if blas_threads is not None:
        env["BUBSUB_BLAS_THREADS"] = str(blas_threads) if blas_threads > 0 else ""
    return subprocess.Popen([sys.executable, "-m", "bubsub.service", "--host", "127.0.0.1", "--port", str(port)],
                            env=env)


def _vertices(surfaces):
    return np.concatenate([s.vertices for s in surfaces])


def run_case(client, case, iterations, repeats, rounds=3, block=5):
    """Median local and remote fit and objective times, and the fitted meshes' largest difference.

    Fits are timed whole, local and remote interleaved. Single objective
    evaluations are timed in alternating blocks (``rounds`` x ``block`` local,
    then as many remote, each block after one untimed call), so that neither
    side is timed right after the other: on a small machine the BLAS threads
    of the side that just computed keep spinning for a moment and would slow
    the other.
    """
    local = MeshProjector(case.geometry)
    target = case.target
    job = client.create_job(case.geometry, data=case.data, background=case.background, surfaces=case.init)
    try:
        local.objective(case.init, target)  # warm-up (imports, first Embree scene)
        job.objective(case.init)
        e_local, e_remote = [], []
        for _ in range(rounds):
            for fn, out in ((lambda: local.objective(case.init, target), e_local),
                            (lambda: job.objective(case.init), e_remote)):
                fn()
                for _ in range(block):
                    t0 = time.perf_counter()
                    fn()
                    out.append(time.perf_counter() - t0)
        t_local, t_remote = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            res_local = fit(local, case.init, target, iterations=iterations, progress=False)
            t_local.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            res_remote = fit(job, case.init, iterations=iterations, progress=False)
            t_remote.append(time.perf_counter() - t0)
    finally:
        job.delete()
    tl, tr = statistics.median(t_local), statistics.median(t_remote)
    el, er = statistics.median(e_local), statistics.median(e_remote)
    return {
        "eval_local_ms": 1e3 * el,
        "eval_remote_ms": 1e3 * er,
        "eval_overhead": er / el - 1.0,
        "case": case.name,
        "unknowns": case.unknowns,
        "evals": res_remote.evaluations,
        "local": tl,
        "remote": tr,
        "overhead": tr / tl - 1.0,
        "max_dx": float(np.max(np.abs(_vertices(res_remote.surfaces) - _vertices(res_local.surfaces)))),
        "f": res_remote.objective,
    }


def format_table(rows):
    """The result table as text."""
    head = ("case", "unknowns", "evals", "fit local s", "fit remote s", "fit overhead",
            "eval local ms", "eval remote ms", "eval overhead", "max |dx| mm")
    lines = [head]
    for r in rows:
        lines.append((r["case"], str(r["unknowns"]), str(r["evals"]), f"{r['local']:.2f}", f"{r['remote']:.2f}",
                      f"{100 * r['overhead']:+.1f} %", f"{r['eval_local_ms']:.1f}", f"{r['eval_remote_ms']:.1f}",
                      f"{100 * r['eval_overhead']:+.1f} %", f"{r['max_dx']:.1e}"))
    widths = [max(len(line[i]) for line in lines) for i in range(len(head))]
    out = []
    for k, line in enumerate(lines):
        out.append(" | ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(line, widths))))
        if k == 0:
            out.append("-+-".join("-" * w for w in widths))
    return "\n".join(out)


def main(argv=None):
    """Run the benchmark; returns 0 (or 1 with ``--check`` when an overhead exceeds 10 %)."""
    ap = argparse.ArgumentParser(prog="python -m bubsub.bench remote", description=__doc__.split("\n\n")[0])
    ap.add_argument("--url", help="use this running server instead of starting one")
    ap.add_argument("--token", default=os.environ.get("BUBSUB_TOKEN"), help="bearer token for --url")
    ap.add_argument("--iterations", type=int, default=40, help="BFGS iterations per fit (default 40)")
    ap.add_argument("--repeats", type=int, default=3, help="fits per side; the median is reported (default 3)")
    ap.add_argument("--cases", default="2d,3d", help="comma-separated: 2d, 3d (default both)")
    ap.add_argument("--blas-threads", type=int, default=1,
                    help="BLAS threads on both sides, so that both compute alike (server: BUBSUB_BLAS_THREADS; "
                         "0 leaves both alone; default 1, the server's default)")
    ap.add_argument("--check", action="store_true", help="exit 1 if an overhead exceeds 10 %%")
    args = ap.parse_args(argv)

    makers = {"2d": case_2d, "3d": case_3d}
    wanted = [c.strip().lower() for c in args.cases.split(",") if c.strip()]
    unknown = [c for c in wanted if c not in makers]
    if unknown:
        ap.error(f"unknown cases {unknown}; choose from {sorted(makers)}")

    proc = None
    url = args.url
    if url is None:
        port = _free_port()
        proc = start_server(port, blas_threads=args.blas_threads)
        url = f"http://127.0.0.1:{port}"
    rows = []
    limiter = None
    if args.blas_threads > 0:
        try:
            from threadpoolctl import threadpool_limits

            limiter = threadpool_limits(limits=args.blas_threads, user_api="blas")
        except ImportError:  # pragma: no cover - threadpoolctl comes with the service extra
            print("threadpoolctl missing: local BLAS threads not limited", file=sys.stderr)
    try:
        with ProjectorClient(url, token=args.token, timeout=600) as client:
            client.wait_ready(60)
            for name in wanted:
                case = makers[name]()
                rows.append(run_case(client, case, args.iterations, args.repeats))
    finally:
        if limiter is not None:
            limiter.restore_original_limits()
        if proc is not None:
            proc.terminate()
            proc.wait(30)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    blas = args.blas_threads if args.blas_threads > 0 else "default"
    print(f"remote fit over loopback ({url}), {args.iterations} BFGS iterations, median of {args.repeats}; "
          f"BLAS threads {blas} on both sides; {os.cpu_count()} cores, load average {load:.1f} at the end "
          f"(should be < 1 for clean timings)")
    print(format_table(rows))
    worst = max(r["overhead"] for r in rows)
    verdict = "PASS" if worst <= TARGET_OVERHEAD else "FAIL"
    print(f"{verdict}: largest remote fit overhead {100 * worst:+.1f} % (target <= {100 * TARGET_OVERHEAD:.0f} %); "
          f"largest per-evaluation overhead {100 * max(r['eval_overhead'] for r in rows):+.1f} %")
    return 1 if (args.check and worst > TARGET_OVERHEAD) else 0


if __name__ == "__main__":
    sys.exit(main())
