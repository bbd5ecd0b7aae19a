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

The column case (``--column N``): a simulated synchrotron foam column of
about N bubbles (:mod:`bubsub.core.foam.column`; ``--column-data DIR``
reuses a simulation folder), reconstructed by ``bubsub reconstruct`` with
its defaults (options this benchmark does not know go to it; ``--rec DIR``
scores an existing reconstruction instead) and by the classic voxel route on
the same scan: SIRT (``--sirt-iterations``, 100) of the bubbles' signal
``(data - background) / contrast`` on the evaluation grid (parallel beam:
every slice on its own), Otsu within the liquid cylinder plus an opening
(:func:`bubsub.core.voxel.segment.binarise`), then FoamQuant's watershed
bubble segmentation (:func:`watershed_bubbles`). Both are scored inside the
field of view (:mod:`bubsub.bench.matching`: found with IoU >= 0.5, missed,
merged, spurious; the cut bubbles apart; DDI).

``python -m bubsub.bench fov --column 600 --column-data /data/column600 [--out DIR] [RECONSTRUCT OPTIONS]``

The local-tomography cases (``--local``, ``--local-ideal``, ``--inside``):
:mod:`bubsub.bench.fov_local`.

``python -m bubsub.bench fov --local 0 1 2 [--local-center auto|given] [--local-radius fitted|given|exact]
[--local-passes N] [--local-term eliminated|alternated] [--local-contrast again|prepared]
[--local-final-refit on|off] [--local-double-flat auto|on|off] [--out DIR]``

``python -m bubsub.bench fov --local-background 0 1 2 3 4 5 6 7 [--out DIR]``

``python -m bubsub.bench fov --local-axis 0 1 2 ... 19 [--out DIR]``

``python -m bubsub.bench fov --local-ideal 0 --local-extend 1.25 1.6``

``python -m bubsub.bench fov --inside 0 1 2 [--out DIR]``
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy import ndimage
from skimage.feature import peak_local_max
from skimage.filters import gaussian
from skimage.segmentation import watershed

from bubsub.bench.fov_local import (LOCAL_FOAMS, print_inside, print_local, print_local_axis, print_local_background,
                                    print_local_ideal)
from bubsub.clients.pipeline.static.detector_term import DETECTOR_TERM_METHOD, DETECTOR_TERM_PASSES, TERM_METHODS
from bubsub.bench.matching import column_truth, mesh_labels, truth_labels
from bubsub.bench.reconstruct import cli_command as _cli
from bubsub.bench.scale import run_tree, simulate_case, table
from bubsub.clients.pipeline.inputs.fov import field_of_view, fov_mask, truncated_flags
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, reconstruct
from bubsub.core import MeshProjector
from bubsub.core.foam.containers import sphere_mesh
from bubsub.core.io.meshio import read_ply
from bubsub.core.io.scanfile import Scan, read_scan
from bubsub.core.matching import match
from bubsub.core.metrics import bubble_mask, dice_dissimilarity
from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.projection.mesh import Mesh
from bubsub.core.projection.masks import pixel_centres
from bubsub.core.voxel.reconstruct3d import reconstruct_3d
from bubsub.core.voxel.segment import binarise

__all__ = ["fov_phantom", "fov_scan", "fov_ddi", "watershed_bubbles", "voxel_route", "column_case", "main"]

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
    if kind == "parallel":
        return ScanGeometry.parallel(np.linspace(0, np.pi, 60, endpoint=False), pixel_size=0.05, cols=96, rows=48)
    return ScanGeometry.cone(np.linspace(0, 2 * np.pi, 60, endpoint=False), source_origin=20.0,
                             origin_detector=20.0, pixel_size=0.1, cols=96, rows=48)


def fov_scan(kind, truth, *, noise=0.003, seed=1):
    """Background-subtracted :class:`Scan` of the truth meshes with Gaussian noise (line-integral units)."""
    g = fov_geometry(kind)
    clean = MeshProjector(g).forward(truth)
    data = clean + np.random.default_rng(seed).normal(0, noise, clean.shape)
    return Scan(data=data.astype(np.float32), geometry=g, bubble_contrast=CONTRAST)


def fov_ddi(rec_meshes, truth_mesh, fov, voxel=0.025):
    """DDI of the reconstruction against one truth bubble, inside its box and the field of view.

    Returns NaN when the truth bubble has no part inside the field of view.
    """
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


def watershed_bubbles(mask, sig_seeds=1.0, sig_watershed=1.0, min_distance=1):
    """FoamQuant's bubble segmentation (``foamquant.Process.BubbleSegmentation`` with its defaults).

    The Euclidean distance map of the gas mask, smoothed by a Gaussian
    (``sig_seeds`` voxels), gives the seeds as its local maxima
    (``peak_local_max``, border included; touching maxima are one seed), and
    the watershed of the negated map smoothed by ``sig_watershed`` grows them
    within the mask. Written here with scikit-image, the package FoamQuant
    calls, because FoamQuant itself pulls in spam, VTK, gmsh and pandas 3.

    Parameters
    ----------
    mask : (slices, rows, cols) bool
    sig_seeds, sig_watershed : float
    min_distance : int
        Of ``peak_local_max``, voxels.

    Returns
    -------
    (slices, rows, cols) int32
        Bubble labels 1..n, 0 outside the mask.
    """
    dist = ndimage.distance_transform_edt(mask)
    peaks = peak_local_max(gaussian(dist, sigma=sig_seeds), min_distance=int(min_distance), exclude_border=False)
    seeds = np.zeros(mask.shape, bool)
    seeds[tuple(peaks.T)] = True
    return watershed(-gaussian(dist, sigma=sig_watershed), ndimage.label(seeds)[0], mask=mask).astype(np.int32)


def voxel_route(scan, meta, iterations=100):
    """SIRT + Otsu + watershed labels of a column scan on its evaluation grid (see the module docstring)."""
    shape, extent = tuple(meta["grid_shape"]), tuple(meta["grid_extent"])
    gas = scan.bubble_data / scan.bubble_contrast  # chord lengths through gas, mm
    image = reconstruct_3d("sirt", gas, scan.geometry, shape, extent, iterations=iterations)
    _, y, x = pixel_centres(shape, extent)
    liquid = np.broadcast_to(np.hypot(x[None, :], y[:, None]) <= meta["column"]["radius_mm"], shape)
    mask = binarise(image, opening_radius=1, bubbles_are_dark=False, roi=liquid)
    return watershed_bubbles(mask)


def column_case(args, extra):
    """The column case's rows: (route, scores, seconds, peak RSS MiB or None)."""
    out = Path(args.out)
    sim, _ = simulate_case(Path(args.column_data) if args.column_data else out / f"column{args.column}", args.column)
    meta, tab = column_truth(sim)
    truth = truth_labels(meta, tab)
    cut = (tab["cut_top"] > 0) | (tab["cut_bottom"] > 0)
    rows = []
    if args.rec:
        rec, seconds, rss = Path(args.rec), None, None
    else:
        rec = out / "bubsub"
        seconds, _, rss = run_tree(_cli("reconstruct", sim / "scan.h5", "--out", rec, "--quiet", "--overwrite", *extra))
    rows.append((f"bubsub reconstruct (from {rec})" if args.rec else "bubsub reconstruct " + (" ".join(extra) or "(defaults)"),
                 match(truth, mesh_labels(read_ply(rec / "bubbles.ply"), meta), cut), seconds, rss))
    t0 = time.perf_counter()
    labels = voxel_route(read_scan(sim / "scan.h5"), meta, args.sirt_iterations)
    c = meta["column"]
    labels[~fov_mask(labels.shape, tuple(meta["grid_extent"]), (c["fov_radius_mm"], c["fov_half_height_mm"]))] = 0
    rows.append((f"SIRT {args.sirt_iterations} + Otsu + watershed", match(truth, labels, cut),
                 time.perf_counter() - t0, None))
    return sim, meta, rows


def _print_column(args, extra):
    sim, meta, rows = column_case(args, extra)
    c = meta["column"]
    print(f"column {sim}: {meta['bubbles']} bubbles in the field of view, {c['bubbles_cut_top']} cut by the top and "
          f"{c['bubbles_cut_bottom']} by the bottom row; {meta['angles']} x {c['rows']} x {c['cols']}; scored on "
          f"{' x '.join(map(str, meta['grid_shape']))} voxels inside the field of view\n")
    keys = ("truth", "found", "missed", "merged", "spurious", "cut_truth", "cut_found", "cut_missed", "cut_merged")
    body = [[name] + [str(r[k]) for k in keys] + [f"{r['ddi']:.4f}", f"{r['median_iou']:.3f}",
                                                   "" if s is None else f"{s:.0f}", "" if m is None else f"{m:.0f}"]
            for name, r, s, m in rows]
    print(table(["route", "truth", "found", "missed", "merged", "spurious", "cut", "cut found", "cut missed",
                 "cut merged", "DDI in FOV", "median IoU (found)", "seconds", "peak RSS MiB"], body))
    return 0


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m bubsub.bench fov", description=__doc__.splitlines()[0])
    ap.add_argument("--geometry", nargs="+", default=["parallel", "cone"], choices=["parallel", "cone"])
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--variants", nargs="+", default=["on", "off"], choices=["on", "off"])
    ap.add_argument("--wide", action="store_true", help="add five bubbles at 1.1-1.4 times the field of view's radius")
    col = ap.add_argument_group("the column case (other options go to bubsub reconstruct)")
    col.add_argument("--column", type=int, metavar="N", help="a simulated foam column of about N bubbles")
    col.add_argument("--column-data", metavar="DIR", help="its simulation folder (made there when missing)")
    col.add_argument("--rec", metavar="DIR", help="score this bubsub reconstruct output instead of running one")
    col.add_argument("--sirt-iterations", type=int, default=100, help="of the voxel route (default 100)")
    col.add_argument("--out", default="bench-fov", help="folder of the column case's outputs (default bench-fov)")
    loc = ap.add_argument_group("the local-tomography case")
    loc.add_argument("--local", type=int, nargs="+", metavar="SEED", help="simulated raw scans of these seeds")
    loc.add_argument("--local-center", choices=["auto", "given"], default="auto",
                     help="prepare's --center: auto, or the true axis given (default auto)")
    loc.add_argument("--local-radius", choices=["fitted", "given", "exact"], default="fitted",
                     help="the liquid cylinder's radius fitted by prepare (default) or given (--liquid-radius); "
                          "exact: the liquid's exact projection as background and the true contrast")
    loc.add_argument("--local-passes", type=int, default=DETECTOR_TERM_PASSES, metavar="N",
                     help="with --local: refits of the detector's view-constant term (clients/pipeline/static/"
                          f"detector_term.py; default {DETECTOR_TERM_PASSES}, 0: none)")
    loc.add_argument("--local-term", choices=TERM_METHODS, default=DETECTOR_TERM_METHOD,
                     help="with --local: how the detector's view-constant term is fitted with the bubbles "
                          f"(default {DETECTOR_TERM_METHOD})")
    loc.add_argument("--local-contrast", choices=["again", "prepared"], default="again",
                     help="with --local: the contrast estimated again once the detector term is out (default), "
                          "or the prepared one kept")
    loc.add_argument("--local-final-refit", choices=["on", "off"], default="on",
                     help="with --local: every bubble refitted last with the detector term eliminated (default on; "
                          "clients/pipeline/static/detector_term.py FINAL_REFIT)")
    loc.add_argument("--local-double-flat", choices=["auto", "on", "off"], default="auto",
                     help="with --local and --local-background: prepare's --double-flat (default auto: the pixel "
                          "gains that the flats do not show divided out before phase retrieval)")
    loc.add_argument("--local-foam", choices=sorted(LOCAL_FOAMS), default="standard",
                     help="with --local and --local-background: the simulated foam (bench/fov_local.py LOCAL_FOAMS: "
                          "standard, large bubbles, small bubbles, a liquid twice the field of view)")
    loc.add_argument("--local-reach", type=float, default=None, metavar="R",
                     help="with --local: the field-of-view radii beyond which prepare takes the foam into the "
                          "background (default core/prep/background.py FOAM_BEYOND_REACH; inf: the liquid alone)")
    loc.add_argument("--local-background", type=int, nargs="+", metavar="SEED",
                     help="the background alone against the liquid's exact projection (local_background_case)")
    loc.add_argument("--local-axis", type=int, nargs="+", metavar="SEED",
                     help="the axis alone: prepare --center auto on these seeds' raw scans (local_axis_case)")
    loc.add_argument("--local-ideal", type=int, nargs="+", metavar="SEED",
                     help="the reconstruction side alone: exact projections and background (local_ideal_case)")
    loc.add_argument("--local-extend", type=float, nargs="+", default=[1.25], metavar="F",
                     help="with --local-ideal: the preview's radius over the field of view's (default 1.25)")
    ap.add_argument("--inside", type=int, nargs="+", metavar="SEED",
                    help="raw scans of a liquid cylinder just inside the detector, these seeds (inside_case)")
    args, extra = ap.parse_known_args(argv)
    if args.column is not None:
        return _print_column(args, extra)
    if args.local:
        return print_local(args)
    if args.local_background:
        return print_local_background(args)
    if args.local_axis:
        return print_local_axis(args)
    if args.local_ideal:
        return print_local_ideal(args)
    if args.inside:
        return print_inside(args)
    if extra:
        ap.error(f"unrecognized arguments: {' '.join(extra)}")
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
