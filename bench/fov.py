"""Bubbles cut by the field of view: accuracy with and without modelling its boundary.

A simulated 3D scan (parallel beam over 180 degrees, or cone beam over 360)
whose sample is larger than what the detector sees: bubbles fully inside
the field of view (the cylinder every projection sees, its height the
detector's), bubbles cut by the detector's top or bottom edge, bubbles
partly outside the reconstructable cylinder (a detector narrower than the
sample, as a ROI), and one bubble wholly outside it but in some
projections. The truth is slightly ellipsoidal icospheres (4 subdivisions,
5120 triangles), projected exactly, with Gaussian noise.

For each variant (``--fov-model`` on or off) the table gives, per class of
bubble, the mean DDI restricted to the field of view (each truth bubble's
box intersected with the field of view; the reconstruction's union against
that bubble), the number of truth bubbles of the class with a
reconstructed bubble whose centroid lies inside the truth bubble's box, the
truncated flags given to that class and the seconds.

``python -m bubsub.bench fov [--geometry parallel cone] [--iterations 60]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np

__all__ = ["fov_phantom", "fov_scan", "fov_ddi", "main"]

#: (centre mm, radius mm, class): field of view radius 2.4 mm, half height 1.2 mm
LAYOUT = (
    ((0.0, 0.0, 0.0), 0.45, "inside"),
    ((1.0, 0.65, 0.3), 0.4, "inside"),
    ((-0.95, 0.8, -0.3), 0.4, "inside"),
    ((0.3, -1.15, 0.2), 0.4, "inside"),
    ((-1.05, -0.6, 0.35), 0.35, "inside"),
    ((0.9, -0.25, 1.2), 0.45, "top/bottom"),
    ((-0.4, 1.25, -1.05), 0.4, "top/bottom"),
    ((2.3, 0.3, -0.2), 0.45, "side"),
    ((-1.65, -1.75, 0.0), 0.4, "side"),
    ((0.2, 2.95, 0.4), 0.35, "outside"),
)
#: ``--wide``: a sample much wider than the field of view, more bubbles wholly outside it
WIDE = (
    ((-2.9, 0.9, -0.5), 0.45, "outside"),
    ((2.2, -2.1, 0.6), 0.4, "outside"),
    ((-1.2, -2.9, -0.4), 0.45, "outside"),
    ((3.1, 1.4, 0.1), 0.4, "outside"),
    ((-2.6, 1.9, 0.7), 0.35, "side"),
)
CONTRAST = -0.1


def fov_phantom(seed=0, wide=False):
    """Truth meshes: ellipsoids (axes 1.1 : 1 : 0.92, random orientation) of :data:`LAYOUT` (and
    :data:`WIDE`), and their classes."""
    from bubsub.core.foam.containers import sphere_mesh
    from bubsub.core.projection.mesh import Mesh

    rng = np.random.default_rng(seed)
    meshes, classes = [], []
    for centre, r, cls in LAYOUT + (WIDE if wide else ()):
        m = sphere_mesh((0, 0, 0), r, CONTRAST, subdivisions=4)
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        v = (np.asarray(m.vertices) @ q) * np.array([1.1, 1.0, 0.92]) @ q.T + np.asarray(centre)
        meshes.append(Mesh(v, m.faces, CONTRAST))
        classes.append(cls)
    return meshes, classes


def fov_geometry(kind):
    """The scans' geometries: 96 x 48 detector, field of view radius 2.4 mm, half height 1.2 mm."""
    from bubsub.core.projection.geometry import ScanGeometry

    if kind == "parallel":
        return ScanGeometry.parallel(np.linspace(0, np.pi, 60, endpoint=False), pixel_size=0.05, cols=96, rows=48)
    return ScanGeometry.cone(np.linspace(0, 2 * np.pi, 60, endpoint=False), source_origin=20.0,
                             origin_detector=20.0, pixel_size=0.1, cols=96, rows=48)


def fov_scan(kind, truth, *, noise=0.003, seed=1):
    """Background-subtracted :class:`Scan` of the truth meshes with Gaussian noise (line-integral units)."""
    from bubsub.core import MeshProjector
    from bubsub.core.io.scanfile import Scan

    g = fov_geometry(kind)
    clean = MeshProjector(g).forward(truth)
    data = clean + np.random.default_rng(seed).normal(0, noise, clean.shape)
    return Scan(data=data.astype(np.float32), geometry=g, bubble_contrast=CONTRAST)


def fov_ddi(rec_meshes, truth_mesh, fov, voxel=0.025):
    """DDI of the reconstruction against one truth bubble, inside its box and the field of view.

    Returns NaN when the truth bubble has no part inside the field of view.
    """
    from bubsub.core.metrics import bubble_mask, dice_dissimilarity
    from bubsub.clients.pipeline.fov import fov_mask

    v = np.asarray(truth_mesh.vertices)
    lo, hi = v.min(0), v.max(0)
    pad = 0.25 * (hi - lo)
    lo, hi = lo - pad, hi + pad
    shape = tuple(int(np.ceil((hi[i] - lo[i]) / voxel)) for i in (2, 1, 0))
    extent = (lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])
    keep = fov_mask(shape, extent, fov)
    if not keep.any():
        return float("nan")
    rec = bubble_mask(rec_meshes, shape, extent) if rec_meshes else np.zeros(shape, bool)
    tru = bubble_mask([truth_mesh], shape, extent)
    if not tru[keep].any():
        return float("nan")
    return dice_dissimilarity(rec[keep], tru[keep])


def run(kind, fov_model, iterations, seed=0, wide=False):
    """One reconstruction; returns ``{class: (ddi list, found, flagged, n)}`` and seconds."""
    from bubsub.clients.pipeline.fov import field_of_view, truncated_flags
    from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, reconstruct

    truth, classes = fov_phantom(seed, wide)
    scan = fov_scan(kind, truth)
    fov = field_of_view(scan.geometry)
    t0 = time.perf_counter()
    # preview voxels of one detector pixel (the default, the field of view over 160, would oversample this detector)
    rec = reconstruct(scan, ReconstructionSettings(iterations=iterations, progress=False, fov_model=fov_model,
                                                   voxel_size=0.05))
    seconds = time.perf_counter() - t0
    fine = [s.fine() for s in rec.surfaces]
    centroids = np.array([m.vertices.mean(0) for m in fine]) if fine else np.zeros((0, 3))
    pixel = rec.report["field_of_view_mm"]["margin"]
    rec_flags = truncated_flags(fine, fov, pixel)
    out = {}
    for mesh, cls in zip(truth, classes):
        v = np.asarray(mesh.vertices)
        lo, hi = v.min(0), v.max(0)
        inside = np.all((centroids >= lo) & (centroids <= hi), axis=1) if len(centroids) else np.zeros(0, bool)
        entry = out.setdefault(cls, {"ddi": [], "found": 0, "flagged": 0, "n": 0})
        entry["ddi"].append(fov_ddi(fine, mesh, fov))
        entry["found"] += int(inside.any())
        entry["flagged"] += int(any(rec_flags[i] for i in np.flatnonzero(inside)))
        entry["n"] += 1
    return out, seconds, len(fine)


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m bubsub.bench fov", description=__doc__.splitlines()[0])
    ap.add_argument("--geometry", nargs="+", default=["parallel", "cone"], choices=["parallel", "cone"])
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--variants", nargs="+", default=["on", "off"], choices=["on", "off"])
    ap.add_argument("--wide", action="store_true", help="add five bubbles at 1.1-1.4 times the field of view's radius")
    args = ap.parse_args(argv)
    print("| geometry | FOV model | class | bubbles | found | flagged truncated | DDI in FOV (mean) | DDI max | "
          "bubbles reconstructed | seconds |")
    print("|---|---|---|---|---|---|---|---|---|---|", flush=True)
    for kind in args.geometry:
        for variant in args.variants:
            res, seconds, n_rec = run(kind, variant == "on", args.iterations, wide=args.wide)
            for cls in ("inside", "top/bottom", "side", "outside"):
                e = res[cls]
                d = np.array([x for x in e["ddi"] if np.isfinite(x)])
                mean = f"{d.mean():.3f}" if len(d) else "n/a"
                worst = f"{d.max():.3f}" if len(d) else "n/a"
                print(f"| {kind} | {variant} | {cls} | {e['n']} | {e['found']} | {e['flagged']} | {mean} | {worst} | "
                      f"{n_rec} | {seconds:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
