"""Benchmark "deadline": how soon a projector server answers a computation past its compute timeout.

A server (``python -m bubsub.service`` on a loopback port, one worker) with
``BUBSUB_COMPUTE_TIMEOUT_SECONDS`` (default 1 s) gets a job far heavier than
that: 40 bubbles (icosphere control meshes of 42 vertices, 3 Loop levels:
5,120 triangles each, seeded positions and radii) on a cone-beam scan of 120
views of 512 x 512 pixels at supersampling 4 (the whole forward takes about
30 s on two threads). It then times, per operation (``forward``, ``vjp`` with
a residual of ones, ``objective`` against the job's uploaded data), the wall
seconds from sending the request to its answer, and prints their median and
largest with the status codes, and the seconds the server's compute worker
spent per call (``/metrics``). A kept deadline answers 504 a few hundredths
of a second past the timeout; the time to send a body (vjp's residual is
126 MB) comes on top of the wall seconds.

``--src DIR`` runs the server from another source tree (a folder holding a
``bubsub`` package), so that two versions compare on one machine in one run.
"""

from __future__ import annotations

import argparse
import io
import re
import statistics
import time

import httpx
import numpy as np

from bubsub.bench.service_harness import NPY, ServerProcess, npy
from bubsub.core import ScanGeometry, sphere_surface

__all__ = ["issue_case", "main"]

GiB = 1 << 30


def issue_case(n_bubbles=40, levels=3, n_angles=120, det=512, seed=0):
    """``(geometry, surfaces)``: the heavy scan and bubbles described in the module docstring."""
    g = ScanGeometry.cone(np.linspace(0, 2 * np.pi, n_angles, endpoint=False), source_origin=150.0,
                          origin_detector=50.0, pixel_size=0.1, cols=det, rows=det)
    rng = np.random.default_rng(seed)
    surfaces = [sphere_surface(tuple(rng.uniform(-10, 10, 3)), rng.uniform(1.5, 4.0), 1.0, levels=levels)
                for _ in range(n_bubbles)]
    return g, surfaces


def _job_json(geometry, surfaces, supersampling):
    return {"geometry": {"kind": geometry.kind, "vectors": geometry.vectors.tolist(), "det_rows": geometry.det_rows,
                         "det_cols": geometry.det_cols},
            "surfaces": [{"n_control": len(s.control.vertices), "faces": np.asarray(s.control_faces).tolist(),
                          "levels": s.levels, "attenuation": s.attenuation} for s in surfaces],
            "supersampling": supersampling}


def _npz(**arrays):
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _worker_seconds(h):
    """``{op: seconds}`` the server's compute workers spent, from ``/metrics``."""
    text = h.get("/metrics").text
    return {m.group(1): float(m.group(2))
            for m in re.finditer(r'^bubsub_compute_seconds_total\{op="(\w+)"\} (\S+)$', text, re.M)}


def run(timeout=1.0, repeats=3, src=None, threads=2, backend="raster", ops=("forward", "vjp", "objective")):
    """``({op: [(status, seconds), ...]}, {op: worker seconds per call})`` of ``repeats`` calls per
    operation (see the module docstring); the worker's seconds leave out sending and decoding the body."""
    g, surfaces = issue_case()
    x = np.concatenate([s.vertices for s in surfaces])
    env = dict(BUBSUB_WORKERS=1, BUBSUB_COMPUTE_TIMEOUT_SECONDS=timeout, BUBSUB_PROJECTOR_THREADS=threads,
               BUBSUB_BACKEND=backend, BUBSUB_JOB_MAX_BYTES=2 * GiB, BUBSUB_MAX_MEMORY_BYTES=4 * GiB,
               BUBSUB_JOB_COMPUTE_MAX_BYTES=8 * GiB, BUBSUB_MAX_COMPUTE_BYTES=8 * GiB,
               BUBSUB_MAX_BODY_BYTES=GiB // 2, BUBSUB_BODY_TIMEOUT_SECONDS=60)
    bodies = {"forward": (npy(x), NPY["content-type"]), "objective": (npy(x), NPY["content-type"]),
              "vjp": (_npz(vertices=x, residual=np.ones(g.shape, np.float32)), "application/x-npz")}
    out = {op: [] for op in ops}
    with ServerProcess(src, **env) as srv, httpx.Client(base_url=srv.url, timeout=300) as h:
        r = h.post("/v1/jobs", json=_job_json(g, surfaces, 4))
        r.raise_for_status()
        job = r.json()["id"]
        r = h.put(f"/v1/jobs/{job}/data", content=npy(np.zeros(g.shape, np.float32)), headers=NPY)
        r.raise_for_status()
        # kernels compiled (or loaded from numba's cache) before timing: a job of the same surfaces, two views
        small_g, _ = issue_case(n_angles=2, det=64)
        small = h.post("/v1/jobs", json=_job_json(small_g, surfaces, 4)).json()["id"]
        warm = {"forward": _npz(vertices=x), "vjp": _npz(vertices=x, residual=np.ones(small_g.shape, np.float32)),
                "objective": _npz(vertices=x, data=np.zeros(small_g.shape, np.float32))}
        for op in ops:  # a first call that compiles the kernels may itself pass the timeout: again, then
            for _ in range(5):
                r = h.post(f"/v1/jobs/{small}/{op}", content=warm[op], headers={"content-type": "application/x-npz"})
                if r.status_code != 504:
                    break
            r.raise_for_status()
        before = _worker_seconds(h)
        for _ in range(repeats):
            for op in ops:
                body, ctype = bodies[op]
                t0 = time.perf_counter()
                r = h.post(f"/v1/jobs/{job}/{op}", content=body, headers={"content-type": ctype})
                out[op].append((r.status_code, time.perf_counter() - t0))
        after = _worker_seconds(h)
    return out, {op: (after.get(op, 0.0) - before.get(op, 0.0)) / repeats for op in ops}


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m bubsub.bench deadline", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--timeout", type=float, default=1.0, help="BUBSUB_COMPUTE_TIMEOUT_SECONDS (default 1)")
    ap.add_argument("--repeats", type=int, default=3, help="calls per operation (default 3)")
    ap.add_argument("--threads", type=int, default=2, help="BUBSUB_PROJECTOR_THREADS (default 2)")
    ap.add_argument("--backend", default="raster", help="BUBSUB_BACKEND (default raster)")
    ap.add_argument("--ops", default="forward,vjp,objective", help="operations to time (default all three)")
    ap.add_argument("--src", action="append", default=[], metavar="DIR",
                    help="also run the server from this source tree (repeatable); the installed one runs first")
    args = ap.parse_args(argv)
    ops = tuple(o.strip() for o in args.ops.split(",") if o.strip())
    print(f"compute timeout {args.timeout:g} s; 40 bubbles x 5,120 triangles, cone 120 x 512 x 512, supersampling 4, "
          f"{args.threads} threads, {args.backend} backend, one worker")
    rows = []
    for src in [None, *args.src]:
        res, worker = run(args.timeout, args.repeats, src, args.threads, args.backend, ops)
        for op, calls in res.items():
            secs = [s for _, s in calls]
            codes = ",".join(sorted({str(c) for c, _ in calls}))
            rows.append([src or "installed", op, codes, f"{statistics.median(secs):.3f}", f"{max(secs):.3f}",
                         f"{worker[op]:.3f}"])
    header = ["server", "operation", "status", "median s", "largest s", "worker s (mean)"]
    widths = [max(len(str(r[i])) for r in rows + [header]) for i in range(len(header))]
    for r in [header] + rows:
        print("  ".join(str(c).ljust(w) for c, w in zip(r, widths)))
    print(f"wall seconds from sending the request to its answer, {args.repeats} calls per operation; worker s: "
          f"the server's compute worker per call (without sending and decoding the body)")
    return 0
