"""Benchmark "foam3d": the mesh projector's backends on the fixed 100-bubble scene.

Scene: 100 disjoint spherical bubbles (radius 0.6-1.2 mm, 320 triangles each)
in a 20 x 20 x 10 mm box; cone beam, 25 projections over 360 degrees,
256 x 512 detector of 0.06 mm pixels, source 300 mm from the centre,
detector 15 mm behind it. Prints, from one run (so ratios compare like with
like on a noisy machine):

* per backend: median ``objective`` (value and gradient) and ``forward``
  times, their speed-up over the native Embree backend, crossings per second
  per thread, the largest difference to the native projection, and the peak
  Python-heap memory of one objective;
* scaling of the objective with the triangle count (the bubbles as Loop
  subdivision surfaces of 42 control vertices at 1, 2 and 3 levels: 320,
  1280 and 5120 triangles each) and with a 4x larger detector (512 x 1024);
* optionally trimesh's multi-hit ray interface on the same rays (forward only);
* with ``--startup N``: a fresh process's first projection per backend
  (medians of N new interpreters, compiled kernels from numba's disk cache):
  seconds from the interpreter's launch to the imports done and to the
  first ``forward`` of the README's example (2 bubbles, 25 x 64 x 128 cone
  beam) done, and the CPU seconds by then.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
import tracemalloc

import numpy as np

from bubsub.core import MeshProjector, ScanGeometry, sphere_surface
from bubsub.core.projection.backends import NAMES, available_backends
from bubsub.core.foam.phantoms import foam3d_benchmark


def foam3d_geometry(n_angles=25, rows=256, cols=512, pixel_size=0.06):
    """The benchmark's cone-beam scan."""
    angles = np.linspace(0, 2 * np.pi, n_angles, endpoint=False)
    return ScanGeometry.cone(angles, source_origin=300.0, origin_detector=15.0, pixel_size=pixel_size, cols=cols, rows=rows)


def _median_time(fn, repeats):
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def trimesh_forward(geometry, meshes):
    """Forward projection through trimesh's multi-hit ray interface (Embree backend)."""
    import trimesh

    verts, faces, mus, off = [], [], [], 0
    for m in meshes:
        verts.append(m.vertices)
        faces.append(np.asarray(m.faces) + off)
        mus.append(np.full(len(m.faces), m.attenuation))
        off += len(m.vertices)
    scene = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False)
    mu = np.concatenate(mus)
    o, d = geometry.rays()
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    intersector = trimesh.ray.ray_pyembree.RayMeshIntersector(scene)
    loc, ray, tri = intersector.intersects_location(o, d, multiple_hits=True)
    t = np.einsum("ij,ij->i", loc - o[ray], d[ray])
    sign = np.sign(np.einsum("ij,ij->i", scene.face_normals[tri], d[ray]))
    out = np.bincount(ray, weights=mu[tri] * sign * t, minlength=len(o))
    return out.reshape(geometry.shape).astype(np.float32)


def _peak_memory(fn):
    """Peak Python-heap (numpy) memory of one call, MiB."""
    tracemalloc.start()
    fn()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak / 2**20


def subdivided_bubbles(meshes, levels):
    """The benchmark's bubbles as Loop subdivision surfaces (42 control vertices) of ``levels`` levels."""
    out = []
    for m in meshes:
        centre = m.vertices.mean(axis=0)
        radius = float(np.linalg.norm(m.vertices - centre, axis=1).mean())
        out.append(sphere_surface(centre, radius, m.attenuation, control=42, levels=levels))
    return out


def _warm_objective(projector, items):
    """The objective against a target 1 % off the forward projection, as a call of no arguments,
    called once already (compilation, caches)."""
    target = projector.forward(items) * np.float32(1.01)

    def call():
        return projector.objective(items, target)

    call()
    return call


def _objective_time(projector, items, repeats):
    return _median_time(_warm_objective(projector, items), repeats)


def _interleaved_objective_times(cases, backends, threads, repeats):
    """Median objective time per (case label, backend), timed in rounds that visit every case once.

    A machine shared with others drifts by tens of percent within a minute;
    timing the cases one after another put that drift into their ratios
    (the growth), where rounds spread it over all of them alike.
    """
    runs = {(label, name): _warm_objective(MeshProjector(geom, threads=threads, backend=name), items)
            for label, geom, items in cases for name in backends}
    times = {key: [] for key in runs}
    for _ in range(repeats):
        for key, call in runs.items():
            t = time.perf_counter()
            call()
            times[key].append(time.perf_counter() - t)
    return {key: statistics.median(v) for key, v in times.items()}


#: A fresh interpreter's first projection: launch time in argv[1], backend in argv[2]; prints seconds as JSON.
_STARTUP = """
import resource, sys, time, json
launched, backend = float(sys.argv[1]), sys.argv[2]
import numpy as np
from bubsub.core import MeshProjector, ScanGeometry, sphere_surface
imported = time.time() - launched
# the README's first example: 2 bubbles, 25 cone projections of 64 x 128 pixels
geometry = ScanGeometry.cone(np.linspace(0, 2 * np.pi, 25, endpoint=False), source_origin=300.0,
                             origin_detector=15.0, pixel_size=0.06, cols=128, rows=64)
meshes = [sphere_surface([0.5, 0.0, 0.0], 0.8, attenuation=-0.1), sphere_surface([-1.2, 0.4, 0.3], 0.6, attenuation=-0.1)]
t = time.time()
MeshProjector(geometry, backend=backend).forward(meshes)
first = time.time() - t
ru = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"imports": imported, "first": first, "total": time.time() - launched, "cpu": ru.ru_utime + ru.ru_stime}))
"""


def startup_times(backend, runs):
    """Medians over ``runs`` fresh interpreters of the startup seconds of :data:`_STARTUP`."""
    out = []
    for _ in range(runs):
        res = subprocess.run([sys.executable, "-c", _STARTUP, repr(time.time()), backend], capture_output=True,
                             text=True, timeout=600, check=True)
        out.append(json.loads(res.stdout.strip().splitlines()[-1]))
    return {k: statistics.median(r[k] for r in out) for k in out[0]}


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m bubsub.bench projector", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5, help="timed calls per operation (median reported)")
    ap.add_argument("--threads", type=int, default=None, help="worker threads (default: all usable cores)")
    ap.add_argument("--backends", default=",".join(NAMES),
                    help=f"comma-separated backends to time (default: {','.join(NAMES)}); native is the reference")
    ap.add_argument("--no-scaling", action="store_true", help="skip the subdivision-level and detector-size rows")
    ap.add_argument("--trimesh", action="store_true", help="also time trimesh's multi-hit ray interface (slow)")
    ap.add_argument("--startup", type=int, default=0, metavar="N",
                    help="only time a fresh process's first projection per backend, median of N processes")
    args = ap.parse_args(argv)
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    unknown = sorted(set(backends) - set(NAMES))
    if unknown:
        ap.error(f"unknown backend(s) {', '.join(unknown)}; choose from {', '.join(NAMES)}")
    missing = sorted(set(backends) - set(available_backends()))
    if missing:
        ap.error(f"backend(s) {', '.join(missing)} cannot run here")

    if args.startup:
        startup_times(backends[0], 1)  # fills numba's disk cache if it is empty: not timed
        rows = []
        for name in backends:
            t = startup_times(name, args.startup)
            rows.append([name, f"{t['imports']:.2f}", f"{t['first']:.2f}", f"{t['total']:.2f}", f"{t['cpu']:.2f}"])
        _print_table(["backend", "imports done s", "first forward s", "launch to first projection s", "CPU s"], rows)
        print(f"medians of {args.startup} fresh processes each; first forward: the README's example (2 bubbles, "
              f"25 x 64 x 128 cone), backend loading included")
        return 0

    phantom = foam3d_benchmark()
    meshes = list(phantom.bubbles)
    geometry = foam3d_geometry()
    print(f"scene: {len(meshes)} bubbles, {sum(len(m.faces) for m in meshes)} triangles; "
          f"scan: cone, {geometry.n_angles} x {geometry.det_rows} x {geometry.det_cols}")

    results = {}
    for name in backends:
        projector = MeshProjector(geometry, threads=args.threads, backend=name)
        t = time.perf_counter()
        data = projector.forward(meshes)
        t_first = time.perf_counter() - t
        t_obj = _objective_time(projector, meshes, args.repeats)
        t_fwd = _median_time(lambda: projector.forward(meshes), args.repeats)
        crossings = projector.trace(meshes).count
        target = data * np.float32(1.01)
        peak = _peak_memory(lambda: projector.objective(meshes, target))
        results[name] = dict(first=t_first, obj=t_obj, fwd=t_fwd, crossings=crossings, peak=peak, data=data,
                             threads=projector.threads)
    ref = results.get("native")

    print()
    header = ["backend", "objective s", "forward s", "obj. speed-up vs native", "fwd speed-up vs native",
              "M crossings/s/thread", "max |p - p_native|", "peak heap MiB", "first call s"]
    rows = []
    for name, r in results.items():
        rows.append([name, f"{r['obj']:.3f}", f"{r['fwd']:.3f}",
                     f"{ref['obj'] / r['obj']:.1f} x" if ref else "-", f"{ref['fwd'] / r['fwd']:.1f} x" if ref else "-",
                     f"{r['crossings'] / r['obj'] / r['threads'] / 1e6:.2f}",
                     f"{np.abs(r['data'] - ref['data']).max():.1e}" if ref else "-",
                     f"{r['peak']:.0f}", f"{r['first']:.2f}"])
    _print_table(header, rows)
    any_r = next(iter(results.values()))
    print(f"threads={any_r['threads']}, valid crossings per call: {any_r['crossings']:,}; "
          f"objective = value + gradient (crossings/s counts the objective's crossings once)")

    if not args.no_scaling:
        print()
        header = ["case", "triangles"] + [f"{n} objective s" for n in backends] + \
            [f"{n} growth" for n in backends]
        rows = []
        cases = [(f"subdivision level {lv}", geometry, subdivided_bubbles(meshes, lv)) for lv in (1, 2, 3)]
        cases.append(("level 1, detector 4x (512 x 1024)", foam3d_geometry(rows=512, cols=1024, pixel_size=0.03),
                      cases[0][2]))
        times = _interleaved_objective_times(cases, backends, args.threads, args.repeats)
        base = {n: times[(cases[0][0], n)] for n in backends}
        for label, geom, items in cases:
            ntri = sum(len(s.fine().faces) for s in items)
            rows.append([label, f"{ntri:,}"] + [f"{times[(label, n)]:.3f}" for n in backends] +
                        [f"{times[(label, n)] / base[n]:.1f} x" for n in backends])
        _print_table(header, rows)
        print(f"growth: objective time relative to subdivision level 1 on the default detector "
              f"(medians of {args.repeats} rounds, each round timing every case once)")

    if args.trimesh:
        t = time.perf_counter()
        tri = trimesh_forward(geometry, meshes)
        t_tri = time.perf_counter() - t
        best = min(results, key=lambda n: results[n]["obj"])
        print(f"\ntrimesh multi-hit forward (1 run): {t_tri:.3f} s; {best} objective is {t_tri / results[best]['obj']:.1f} x "
              f"faster; pixels where trimesh differs by > 1e-4: {np.mean(np.abs(tri - results[best]['data']) > 1e-4):.2%} "
              f"(its fixed re-cast offset)")
    print(f"\npeak process RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
    return 0


def _print_table(header, rows):
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows)]
    print("  ".join(h.ljust(w) for h, w in zip(header, widths)))
    print("  ".join("-" * w for w in widths))
    for r in rows:
        print("  ".join(str(x).ljust(w) for x, w in zip(r, widths)))
