"""Benchmark "admission": the compute memory estimate against the server's measured peak, per job shape.

``python -m bubsub.bench admission [--only NAME,...] [--repeats R] [--backend NAME] [--csv FILE]``

For each job shape (those of the service tests, and larger ones of the same
kinds) a server process (``python -m bubsub.service``, one worker) creates
the job, its kernels are loaded by the same operation on a small job of the
same kind, and the job's first computation is measured: the rise of the
server's peak resident memory (``VmHWM`` after resetting it through
``/proc/PID/clear_refs``) during that one request. The server runs with
``MALLOC_MMAP_THRESHOLD_`` fixed, so that large arrays are given back when
freed and a peak is not hidden in memory an earlier call left in the heap.
The estimate is :func:`bubsub.service.budget.estimate` for the same job and
vertices (computed here with the server's settings and the same backend and
thread count). Prints estimate, measured peak (median over the repeats, a
fresh server each) and their ratio; the target is a ratio in [1, 1.5].
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import httpx
import numpy as np

from bubsub.core import Polygon, ScanGeometry, SubdivisionSurface, sphere_surface
from bubsub.service.budget import estimate
from bubsub.service.jobs import build_job

__all__ = ["SHAPES", "ENV", "measure", "measure_on", "estimate_bytes", "main"]

MiB = 1 << 20

#: the server's settings while measuring: caps out of the way, one computation at a time
ENV = {
    "BUBSUB_WORKERS": "1",
    "BUBSUB_JOB_MAX_BYTES": str(8 << 30),
    "BUBSUB_MAX_MEMORY_BYTES": str(16 << 30),
    "BUBSUB_JOB_COMPUTE_MAX_BYTES": str(16 << 30),
    "BUBSUB_MAX_COMPUTE_BYTES": str(16 << 30),
    "BUBSUB_MAX_BODY_BYTES": str(2 << 30),
    "MALLOC_MMAP_THRESHOLD_": str(64 << 10),
}


def _cone(n_angles, rows, cols, pixel_size):
    return ScanGeometry.cone(np.linspace(0, 2 * np.pi, n_angles, endpoint=False), source_origin=150.0,
                             origin_detector=50.0, pixel_size=pixel_size, cols=cols, rows=rows)


def _spheres(n, radius, levels, seed=0, spread=6.0):
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-spread, spread, (n, 3)) if n > 1 else np.zeros((1, 3))
    return [sphere_surface(tuple(c), radius, 1.0, levels=levels) for c in centres]


def _triangles(n, scale=0.05):
    tri = np.array([[1.0, 0.0], [-0.5, 0.8], [-0.5, -0.8]]) * scale
    return [SubdivisionSurface(Polygon(tri + [(i % 100) * 0.2 - 10, (i // 100) * 0.2 - 8], 1.0), 6)
            for i in range(n)]


def _detector_1400():
    """tests/test_service_budget.py: one parallel view of 1400 x 1400 pixels nearly filled by a sphere."""
    g = ScanGeometry.from_astra("parallel3d_vec", [[0, 1, 0, 0, 0, 0, 1.4 / 1400, 0, 0, 0, 0, 1.4 / 1400]],
                                det_rows=1400, det_cols=1400)
    return g, _spheres(1, 0.7, 2), 1


#: name -> (what it is, builder of (geometry, surfaces, supersampling), operation)
SHAPES = {
    "detector_1400": ("1 view 1400 x 1400, one sphere (budget test)", _detector_1400, "forward"),
    "heavy_limits": ("24 views 64 x 64, 2 spheres, supersampling 2 (limits test)",
                     lambda: (_cone(24, 64, 64, 0.4), _spheres(2, 3.5, 2, spread=3.0), 2), "objective"),
    "timeout_forward": ("400 views 128 x 128, level-3 sphere, supersampling 4 (timeout test)",
                        lambda: (_cone(400, 128, 128, 0.2), _spheres(1, 8.0, 3), 4), "forward"),
    "timeout_vjp": ("the same, vjp", lambda: (_cone(400, 128, 128, 0.2), _spheres(1, 8.0, 3), 4), "vjp"),
    "foam_objective": ("100 views 128 x 128, 30 level-3 spheres",
                       lambda: (_cone(100, 128, 128, 0.15), _spheres(30, 1.2, 3), 1), "objective"),
    "supersampled_objective": ("40 views 128 x 128, level-3 sphere, supersampling 4 (store overflows)",
                               lambda: (_cone(40, 128, 128, 0.2), _spheres(1, 8.0, 3), 4), "objective"),
    "many_faces_forward": ("8 views 64 x 64, 200 level-4 spheres (4,096,000 faces)",
                           lambda: (_cone(8, 64, 64, 0.3), _spheres(200, 0.5, 4), 1), "forward"),
    "many_faces_objective": ("the same, objective",
                             lambda: (_cone(8, 64, 64, 0.3), _spheres(200, 0.5, 4), 1), "objective"),
    "many_2d_forward": ("2D, 16 views x 256, 1000 triangles at level 6 (budget test's kind)",
                        lambda: (__import__("bubsub.core", fromlist=["ScanGeometry"]).ScanGeometry.parallel(
                            np.linspace(0, np.pi, 16, endpoint=False), pixel_size=1.0, cols=256),
                                 _triangles(1000), 1), "forward"),
    "many_2d_objective": ("the same, objective",
                          lambda: (__import__("bubsub.core", fromlist=["ScanGeometry"]).ScanGeometry.parallel(
                              np.linspace(0, np.pi, 16, endpoint=False), pixel_size=1.0, cols=256),
                                   _triangles(1000), 1), "objective"),
}


def _spec(geometry, surfaces, supersampling):
    """JSON of a job for ``surfaces`` (consecutive surfaces of one topology in one group)."""
    groups = []
    for s in surfaces:
        g = {"n_control": len(s.control.vertices), "levels": s.levels, "attenuation": s.attenuation}
        if geometry.ndim == 3:
            g["faces"] = np.asarray(s.control_faces).tolist()
        if groups and all(groups[-1][key] == value for key, value in g.items()):
            groups[-1]["count"] += 1
        else:
            groups.append({**g, "count": 1})
    geo = {"kind": geometry.kind, "vectors": geometry.vectors.tolist(),
           "det_rows": geometry.det_rows if geometry.ndim == 3 else None,
           "det_cols": geometry.det_cols if geometry.ndim == 3 else geometry.det_count}
    return {"geometry": geo, "surfaces": groups, "supersampling": supersampling}


def _npy(a):
    import io

    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def _npz(**arrays):
    import io

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _request(op, x, shape):
    """``(body, content type, decoded arrays)`` of an ``op`` request (vjp: a float32 residual of ones)."""
    if op == "vjp":
        arrays = {"vertices": x, "residual": np.ones(shape, np.float32)}
        return _npz(**arrays), "application/x-npz", arrays
    return _npy(x), "application/x-npy", {"vertices": x}


def _call(h, url, job, op, x, shape):
    body, ctype, _ = _request(op, x, shape)
    return h.post(f"{url}/v1/jobs/{job}/{op}", content=body, headers={"content-type": ctype})


def _create(h, url, spec, x, data=None):
    files = {"job": (None, json.dumps(spec), "application/json"), "vertices": ("v.npy", _npy(x), "application/x-npy")}
    if data is not None:
        files["data"] = ("d.npy", _npy(data), "application/x-npy")
    r = h.post(f"{url}/v1/jobs", files=files)
    if r.status_code != 201:
        raise RuntimeError(f"job creation failed: {r.status_code} {r.text[:500]}")
    return r.json()["id"]


def estimate_bytes(spec, x, op, env, shape):
    """:func:`bubsub.service.budget.estimate` of ``op`` on the job ``spec`` under the server settings ``env``,
    for the request :func:`_call` sends."""
    import os

    from bubsub.service.config import Settings
    from bubsub.service.schemas import JobCreate

    keys = {k[len("BUBSUB_"):].lower(): v for k, v in {**os.environ, **env}.items() if k.startswith("BUBSUB_")}
    keys.pop("backend", None)  # not a setting: the projector reads it from the environment
    settings = Settings(**keys)
    backend = os.environ.get("BUBSUB_BACKEND")
    os.environ["BUBSUB_BACKEND"] = env.get("BUBSUB_BACKEND", backend or "auto")
    try:
        job = build_job("estimate", "bench", JobCreate(**spec), settings, vertices=x)
    finally:
        if backend is None:
            del os.environ["BUBSUB_BACKEND"]
        else:
            os.environ["BUBSUB_BACKEND"] = backend
    body, _, arrays = _request(op, x, shape)
    return estimate(job, op, settings.crossings_per_ray, job.check_vertices(x), arrays, len(body))


def measure_on(srv, h, name, env=ENV):
    """``(estimate, measured peak rise in bytes)`` of shape ``name``'s first computation on the running
    server ``srv`` (a :class:`~bubsub.bench.service_harness.ServerProcess` started with ``env``; ``h`` an httpx client)."""
    _, build, op = SHAPES[name]
    geometry, surfaces, k = build()
    spec = _spec(geometry, surfaces, k)
    x = np.concatenate([s.vertices for s in surfaces])
    data = np.zeros(geometry.shape, np.float32) if op == "objective" else None
    # the same operation on a small job of the same kind first: kernels loaded, not measured
    warm_geometry = _cone(3, 16, 16, 1.0) if geometry.ndim == 3 else geometry
    warm_data = np.zeros(warm_geometry.shape, np.float32) if op == "objective" else None
    warm = _create(h, srv.url, _spec(warm_geometry, surfaces[:1], k), surfaces[0].vertices, warm_data)
    r = _call(h, srv.url, warm, op, surfaces[0].vertices, warm_geometry.shape)
    if r.status_code != 200:
        raise RuntimeError(f"warm-up {op} failed: {r.status_code} {r.text[:300]}")
    job = _create(h, srv.url, spec, x, data)
    base = srv.reset_peak()
    r = _call(h, srv.url, job, op, x, geometry.shape)
    peak = srv.peak() - base
    if r.status_code != 200:
        raise RuntimeError(f"{name}: {op} failed: {r.status_code} {r.text[:300]}")
    for j in (warm, job):
        h.delete(f"{srv.url}/v1/jobs/{j}")
    return estimate_bytes(spec, x, op, env, geometry.shape), peak


def measure(name, backend=None):
    """One measurement of shape ``name`` on a fresh server: ``(Estimate, measured peak rise in bytes)``."""
    from bubsub.bench.service_harness import ServerProcess

    env = dict(ENV, **({"BUBSUB_BACKEND": backend} if backend else {}))
    with ServerProcess(**env) as srv, httpx.Client(timeout=600) as h:
        return measure_on(srv, h, name, env)


def format_table(rows):
    lines = ["| shape | op | estimate (MB) | measured peak (MB) | estimate / measured |",
             "| --- | --- | ---: | ---: | ---: |"]
    for r in rows:
        lines.append(f"| {r['shape']} | {r['op']} | {r['estimate'] / 1e6:.1f} | {r['measured'] / 1e6:.1f} | "
                     f"{r['ratio']:.2f} |")
    return "\n".join(lines)


def main(argv=None):
    from bubsub.bench.attacks import selected

    parser = argparse.ArgumentParser(prog="python -m bubsub.bench admission", description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", help="comma-separated shapes (default: all): " + ", ".join(SHAPES))
    parser.add_argument("--repeats", type=int, default=3, help="fresh servers per shape (median)")
    parser.add_argument("--backend", help="BUBSUB_BACKEND of the server (default: its own choice)")
    parser.add_argument("--json", help="also write the rows to this file")
    args = parser.parse_args(argv)
    names = selected(parser, args.only, SHAPES)
    rows = []
    for name in names:
        runs = [measure(name, args.backend) for _ in range(max(1, args.repeats))]
        need = runs[0][0]
        measured = statistics.median(p for _, p in runs)
        row = {"shape": name, "op": SHAPES[name][2], "what": SHAPES[name][0], "estimate": need.total,
               "measured": measured, "ratio": need.total / max(measured, 1), "parts": need.__dict__,
               "runs": [p for _, p in runs]}
        print(f"{name}: estimate {need.total / 1e6:.1f} MB, measured {measured / 1e6:.1f} MB "
              f"(runs {', '.join(f'{p / 1e6:.1f}' for _, p in runs)}), ratio {row['ratio']:.2f}; {need.describe()}",
              flush=True)
        rows.append(row)
    print()
    print(format_table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=str))
    return 0
