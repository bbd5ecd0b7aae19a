"""Benchmark "foam3d": the mesh projector on the fixed 100-bubble scene.

Scene: 100 disjoint spherical bubbles (radius 0.6-1.2 mm, 320 triangles each)
in a 20 x 20 x 10 mm box; cone beam, 25 projections over 360 degrees,
256 x 512 detector of 0.06 mm pixels, source 300 mm from the centre,
detector 15 mm behind it. Prints one table: median times of ``objective``
(value and gradient) and ``forward``, crossings per second, peak memory, and
trimesh's multi-hit ray interface on the same rays (forward only).
"""

from __future__ import annotations

import argparse
import resource
import statistics
import time
import tracemalloc

import numpy as np

from bubsub.core import MeshProjector, ScanGeometry
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


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m bubsub.bench projector", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5, help="timed calls per operation (median reported)")
    ap.add_argument("--threads", type=int, default=None, help="ray-casting threads (default: all usable cores)")
    ap.add_argument("--backend", choices=["auto", "native", "embreex"], default="auto", help="ray-casting backend (see MeshProjector)")
    ap.add_argument("--no-trimesh", action="store_true", help="skip the trimesh comparison")
    ap.add_argument("--no-compare", action="store_true", help="skip timing the other backend")
    args = ap.parse_args(argv)

    phantom = foam3d_benchmark()
    meshes = list(phantom.bubbles)
    geometry = foam3d_geometry()
    projector = MeshProjector(geometry, threads=args.threads, backend=args.backend)
    t = time.perf_counter()
    data = projector.forward(meshes)
    t_first = time.perf_counter() - t
    target = data * np.float32(1.01)
    projector.objective(meshes, target)  # warm-up

    t_obj = _median_time(lambda: projector.objective(meshes, target), args.repeats)
    t_fwd = _median_time(lambda: projector.forward(meshes), args.repeats)
    crossings = projector.trace(meshes).count

    tracemalloc.start()
    projector.objective(meshes, target)
    _, peak_py = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    rows = [
        ("scene", f"{len(meshes)} bubbles, {sum(len(m.faces) for m in meshes)} triangles"),
        ("scan", f"cone, {geometry.n_angles} x {geometry.det_rows} x {geometry.det_cols}, threads={projector.threads}"),
        ("backend", projector.backend),
        ("first forward (compile or cache load)", f"{t_first:.3f} s"),
        ("objective (value+gradient), median", f"{t_obj:.3f} s"),
        ("forward, median", f"{t_fwd:.3f} s"),
        ("valid crossings per call", f"{crossings:,}"),
        ("crossings per second (objective)", f"{crossings / t_obj / 1e6:.2f} M/s"),
        ("peak numpy memory in objective", f"{peak_py / 2**20:.0f} MiB"),
        ("peak process RSS so far", f"{peak_rss:.0f} MiB"),
    ]
    if not args.no_compare and projector.backend == "native":
        other = MeshProjector(geometry, threads=args.threads, backend="embreex")
        t_other = _median_time(lambda: other.objective(meshes, target), args.repeats)
        diff = np.abs(other.forward(meshes) - data).max()
        rows += [("objective, embreex backend, median", f"{t_other:.3f} s"),
                 ("max |forward difference| between backends", f"{diff:.1e}")]
    if not args.no_trimesh:
        t = time.perf_counter()
        ref = trimesh_forward(geometry, meshes)
        t_tri = time.perf_counter() - t
        rows += [
            ("trimesh multi-hit forward (1 run)", f"{t_tri:.3f} s"),
            ("speed-up of objective over trimesh forward", f"{t_tri / t_obj:.1f} x"),
            ("pixels where trimesh differs by > 1e-4", f"{np.mean(np.abs(ref - data) > 1e-4):.2%} (its fixed re-cast offset)"),
        ]
    width = max(len(r[0]) for r in rows)
    print(f"{'benchmark foam3d':<{width}}  value")
    print(f"{'-' * width}  {'-' * 30}")
    for k, v in rows:
        print(f"{k:<{width}}  {v}")
    return 0
