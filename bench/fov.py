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

The local-tomography case (``--local SEED [SEED ...]``): a simulated raw
beamline scan (:mod:`bubsub.core.foam.raw`: flats, darks, 16 keV, 300 mm
Fresnel propagation, the axis 5.3 pixels off centre) of a liquid cylinder
1.5 times the field of view's radius filled with bubbles out to its wall
(:func:`bubsub.core.foam.raw.disc_foam`), run through ``bubsub prepare --bin
2 --delta-beta 1450 --center auto --background auto`` (``--local-center
given`` passes the true axis instead) and ``bubsub reconstruct`` with its
defaults. Scored inside the interior cylinder, the field of view's radius
less one largest bubble's diameter (:func:`interior_scores`): the true
bubbles whose centroid lies there found with IoU >= 0.5, the reconstructed
bubbles there that are no true bubble's best (spurious), the DDI there, and
the axis error.

``python -m bubsub.bench fov --local 0 1 2 [--local-center auto|given] [--out DIR]``

``--local-ideal SEED ... --local-extend 1.25 1.6``: the reconstruction side
alone on exact projections of such a foam with its liquid's exact projection
as background (:func:`local_ideal_case`), the preview's radius for a foam
wider than the detector varied (the design's alternative: every bubble of
the foam in the model).

``python -m bubsub.bench fov --local-ideal 0 --local-extend 1.25 1.6``
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import ndimage
from skimage.feature import peak_local_max
from skimage.filters import gaussian
from skimage.segmentation import watershed

from bubsub.bench.matching import column_truth, mesh_labels, truth_labels
from bubsub.bench.reconstruct import cli_command as _cli
from bubsub.bench.scale import run_tree, simulate_case, table
from bubsub.clients.pipeline import fov as fovmod
from bubsub.clients.pipeline.evaluate import evaluate_dir
from bubsub.clients.pipeline.fov import field_of_view, fov_mask, truncated_flags
from bubsub.clients.pipeline.outputs import write_outputs
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, reconstruct
from bubsub.core import MeshProjector
from bubsub.core.foam.containers import sphere_mesh
from bubsub.core.foam.raw import disc_foam, raw_settings, write_raw_simulation
from bubsub.core.io.meshio import read_ply, read_polygons_json
from bubsub.core.io.scanfile import Scan, read_scan
from bubsub.core.matching import match
from bubsub.core.metrics import bubble_mask, dice_dissimilarity
from bubsub.core.prep import prepare, prepare_options
from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.projection.mesh import Mesh, Polygon
from bubsub.core.voxel.raster import label_image, pixel_centres
from bubsub.core.voxel.reconstruct3d import reconstruct_3d
from bubsub.core.voxel.segment import binarise

__all__ = ["fov_phantom", "fov_scan", "fov_ddi", "watershed_bubbles", "voxel_route", "column_case", "local_case",
           "local_ideal_case", "inside_case", "interior_scores", "main"]

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
    from pathlib import Path


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


#: The local-tomography case's raw scan: 256 columns of 12 um, 90 projections over 180 degrees, 2 rows.
LOCAL_SCAN = {"cols": 256, "pixel_size": 0.012, "axis_offset": 5.3, "n_angles": 90, "rows": 2, "distance": 300.0,
              "supersample": 2}


#: The raw scan of a liquid cylinder inside the detector (:func:`inside_case`): 240 columns of 6 um, 60
#: projections over 180 degrees, 2 rows; the cylinder's edge :data:`INSIDE_MARGIN` binned pixels from each side.
INSIDE_SCAN = {"cols": 240, "pixel_size": 0.006, "axis_offset": 5.3, "n_angles": 60, "rows": 2, "distance": 300.0,
               "supersample": 2}
#: Binned pixels (``--bin 2``) between the liquid cylinder's edge and each side of the axis-centred crop.
INSIDE_MARGIN = 9


def inside_case(out, seed):
    """Simulate, prepare, reconstruct and score a raw scan whose liquid cylinder stands just inside the detector.

    The scan of ``tests/test_truncation.py``: :data:`INSIDE_SCAN` (flats,
    darks, 16 keV, 300 mm, the axis 5.3 pixels off centre), the liquid
    cylinder :data:`INSIDE_MARGIN` binned pixels inside each side of the
    columns ``prepare`` keeps about the axis, holding bubbles of 0.1-0.22
    times its radius (:func:`bubsub.core.foam.raw.disc_foam`, 12 placed);
    phase retrieval spreads its edge into the outermost columns. Through
    ``bubsub prepare --bin 2 --delta-beta 1450 --center auto --background
    auto`` and ``bubsub reconstruct`` with its defaults, scored by
    ``bubsub evaluate`` (:func:`bubsub.clients.pipeline.evaluate.evaluate_dir`).

    Returns
    -------
    dict
        ``ddi``, ``truth``, ``found``, ``spurious``, ``reconstructed``, ``axis_error_px`` (raw pixels),
        ``contrast`` (1/mm), ``prepare_s``, ``reconstruct_s``.
    """
    from pathlib import Path

    c = INSIDE_SCAN
    out = Path(out)
    axis = c["cols"] / 2 - 0.5 + c["axis_offset"]
    crop = int(2 * min(axis + 0.5, c["cols"] - 0.5 - axis)) // 2 * 2  # the columns prepare keeps, raw
    radius = (crop / 4 - INSIDE_MARGIN) * 2 * c["pixel_size"]
    s = raw_settings(seed=seed, container_radius=radius, wall=0.0, **c)
    write_raw_simulation(out, disc_foam(seed, radius, n_bubbles=12, radius_range=(0.1 * radius, 0.22 * radius)), s)
    t0 = time.perf_counter()
    report = prepare(out / "raw.h5", out / "scan.h5", prepare_options(
        roi="1:2,:", bin=2, delta_beta=1450, center="auto", background="auto"), progress=False)
    t1 = time.perf_counter()
    rec = reconstruct(read_scan(out / "scan.h5"), ReconstructionSettings(progress=False))
    t2 = time.perf_counter()
    write_outputs(out / "rec", rec, scan_path=out / "scan.h5")
    res = evaluate_dir(out / "rec", out)
    steps = {x["step"]: x for x in report["steps"]}
    return {"ddi": res["ddi"], "truth": res["bubbles_truth"], "found": res["matching"]["found"],
            "spurious": res["matching"]["spurious"], "reconstructed": res["bubbles_reconstructed"],
            "axis_error_px": steps["center"]["axis_column_raw"] - s.axis_column,
            "contrast": steps["contrast"]["bubble_contrast_per_mm"], "prepare_s": t1 - t0, "reconstruct_s": t2 - t1}


def local_case(out, seed, *, center="auto"):
    """Simulate, prepare, reconstruct and score one local-tomography scan (see the module docstring).

    Returns
    -------
    dict
        :func:`interior_scores` and ``axis_error_px`` (raw pixels), ``center`` (the method or the error),
        ``prepare_s``, ``reconstruct_s``; ``failed`` with the message where prepare stops.
    """
    from pathlib import Path


    out = Path(out)
    c = LOCAL_SCAN
    axis = c["cols"] / 2 - 0.5 + c["axis_offset"]
    half = min(axis + 0.5, c["cols"] - 0.5 - axis) * c["pixel_size"]
    radius = 1.5 * half
    s = raw_settings(seed=seed, container_radius=radius, wall=0.0, wider_than_detector=True, **c)
    write_raw_simulation(out, disc_foam(seed, radius, n_bubbles=80, radius_range=(0.08 * half, 0.15 * half)), s)
    t0 = time.perf_counter()
    try:
        report = prepare(out / "raw.h5", out / "scan.h5", prepare_options(
            roi="1:2,:", bin=2, delta_beta=1450, center="auto" if center == "auto" else s.axis_column,
            background="auto"), progress=False)
    except ValueError as exc:
        return {"failed": str(exc), "prepare_s": time.perf_counter() - t0}
    t1 = time.perf_counter()
    step = next(x for x in report["steps"] if x["step"] == "center")
    scan = read_scan(out / "scan.h5")
    rec = reconstruct(scan, ReconstructionSettings(progress=False))
    t2 = time.perf_counter()
    scores = interior_scores([x.fine() for x in rec.surfaces], read_polygons_json(out / "truth.json"), scan.geometry)
    contrast = next(x for x in report["steps"] if x["step"] == "contrast")["bubble_contrast_per_mm"]
    return {**scores, "axis_error_px": step["axis_column_raw"] - s.axis_column, "center": step["method"],
            "contrast": contrast, "prepare_s": t1 - t0, "reconstruct_s": t2 - t1}


def local_ideal_case(seed, extend):
    """The local-tomography foam on exact projections, its liquid's exact projection as background.

    90 parallel views over 180 degrees of a 128-column detector of 40 um
    pixels; a liquid disc 1.5 times the field of view's radius filled with
    bubbles (:func:`bubsub.core.foam.raw.disc_foam`), projected exactly
    (Gaussian noise 0.003), reconstructed with its defaults but the preview
    out to ``extend`` times the field of view's radius for a foam wider than
    the detector (:data:`bubsub.clients.pipeline.fov.LOCAL_EXTEND`): the
    reconstruction side alone, without the raw scan's preparation.

    Returns
    -------
    dict
        :func:`interior_scores` and ``reconstruct_s``.
    """
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 90, endpoint=False), pixel_size=0.04, cols=128)
    r_fov = fovmod.field_of_view(g)[0]
    radius = 1.5 * r_fov
    phantom = disc_foam(seed, radius, n_bubbles=120, radius_range=(0.06 * r_fov, 0.14 * r_fov))
    t = np.linspace(0, 2 * np.pi, 96, endpoint=False)
    liquid = Polygon(radius * np.stack([np.cos(t), np.sin(t)], 1) / np.cos(np.pi / 96), 0.1)  # circumscribed
    projector = MeshProjector(g, supersampling=2)
    background = projector.forward([liquid])
    data = background + projector.forward(list(phantom.bubbles))
    data += np.random.default_rng(seed).normal(0, 0.003, data.shape)
    scan = Scan(data=data.astype(np.float32), geometry=g, background=background.astype(np.float32),
                bubble_contrast=phantom.contrast)
    before = fovmod.LOCAL_EXTEND
    fovmod.LOCAL_EXTEND = extend
    try:
        t0 = time.perf_counter()
        rec = reconstruct(scan, ReconstructionSettings(progress=False))
        seconds = time.perf_counter() - t0
    finally:
        fovmod.LOCAL_EXTEND = before
    return {**interior_scores([x.fine() for x in rec.surfaces], list(phantom.bubbles), g), "reconstruct_s": seconds}


def interior_scores(rec, truth, geometry, *, pixels=600):
    """Bubbles found, spurious bubbles and DDI inside the interior cylinder of a 2D reconstruction.

    The interior is the field of view's disc shrunk by one largest true
    bubble's diameter: a true bubble whose centroid lies there is wholly
    inside the field of view. Both outline sets are rasterised on a grid
    of ``pixels`` across the field of view (outside it set to 0) and matched
    there (:func:`bubsub.core.matching.match`); a true bubble of the interior
    is found with IoU >= 0.5; a reconstructed bubble whose centroid lies in
    the interior and is no true bubble's best is spurious; the DDI counts the
    interior's pixels.

    Parameters
    ----------
    rec, truth : list of Polygon
    geometry : ScanGeometry
        2D.

    Returns
    -------
    dict
        ``interior_radius_mm``, ``truth``, ``found``, ``found_percent``, ``spurious``, ``ddi``, ``reconstructed``.
    """
    r_fov = field_of_view(geometry)[0]
    r_int = r_fov - 2 * max(np.sqrt(abs(p.area) / np.pi) for p in truth)
    extent = (-r_fov, r_fov, -r_fov, r_fov)
    t_lab, r_lab = label_image(truth, (pixels, pixels), extent), label_image(rec, (pixels, pixels), extent)
    yy, xx = (np.mgrid[:pixels, :pixels] + 0.5) * (2 * r_fov / pixels) - r_fov
    r = np.hypot(xx, yy)
    t_lab[r > r_fov], r_lab[r > r_fov] = 0, 0
    m = match(t_lab, r_lab)
    centre = lambda items: np.array([np.hypot(*np.asarray(p.vertices).mean(axis=0)) for p in items])
    inner_t = set(np.flatnonzero(centre(truth) <= r_int) + 1)
    inner_r = set(np.flatnonzero(centre(rec) <= r_int) + 1) if rec else set()
    found = sum(1 for i, _, _, status in m["per_truth"] if i in inner_t and status == "found")
    owners = {j for _, j, _, _ in m["per_truth"]}
    return {"interior_radius_mm": r_int, "truth": len(inner_t), "found": found,
            "found_percent": 100.0 * found / max(1, len(inner_t)), "spurious": len(inner_r - owners),
            "ddi": float(dice_dissimilarity(r_lab[r <= r_int] > 0, t_lab[r <= r_int] > 0)), "reconstructed": len(rec)}


def _print_local(args):
    from pathlib import Path

    print(f"| seed | centre | axis error (raw px) | contrast (1/mm) | interior bubbles | found (IoU >= 0.5) | spurious "
          f"| DDI (interior) | prepare s | reconstruct s |")
    print("|---|---|---|---|---|---|---|---|---|---|", flush=True)
    for seed in args.local:
        r = local_case(Path(args.out) / f"local{seed}", seed, center=args.local_center)
        if "failed" in r:
            print(f"| {seed} | {args.local_center} | prepare stopped: {r['failed']} | | | | | | "
                  f"{r['prepare_s']:.0f} | |", flush=True)
            continue
        print(f"| {seed} | {args.local_center} | {r['axis_error_px']:+.2f} | {r['contrast']:.4f} | {r['truth']} | "
              f"{r['found']} ({r['found_percent']:.0f} %) | {r['spurious']} | {r['ddi']:.4f} | {r['prepare_s']:.0f} | "
              f"{r['reconstruct_s']:.0f} |", flush=True)
    return 0


def _print_inside(args):
    from pathlib import Path

    print("| seed | axis error (raw px) | contrast (1/mm) | bubbles | found (IoU >= 0.5) | spurious | DDI | prepare s | "
          "reconstruct s |")
    print("|---|---|---|---|---|---|---|---|---|", flush=True)
    for seed in args.inside:
        r = inside_case(Path(args.out) / f"inside{seed}", seed)
        print(f"| {seed} | {r['axis_error_px']:+.2f} | {r['contrast']:.4f} | {r['truth']} | {r['found']} | "
              f"{r['spurious']} | {r['ddi']:.4f} | {r['prepare_s']:.0f} | {r['reconstruct_s']:.0f} |", flush=True)
    return 0


def _print_local_ideal(args):
    print("| seed | preview radius / field of view's | interior bubbles | found (IoU >= 0.5) | spurious | "
          "DDI (interior) | bubbles reconstructed | reconstruct s |")
    print("|---|---|---|---|---|---|---|---|", flush=True)
    for seed in args.local_ideal:
        for extend in args.local_extend:
            r = local_ideal_case(seed, extend)
            print(f"| {seed} | {extend:g} | {r['truth']} | {r['found']} ({r['found_percent']:.0f} %) | {r['spurious']} "
                  f"| {r['ddi']:.4f} | {r['reconstructed']} | {r['reconstruct_s']:.0f} |", flush=True)
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
        return _print_local(args)
    if args.local_ideal:
        return _print_local_ideal(args)
    if args.inside:
        return _print_inside(args)
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
