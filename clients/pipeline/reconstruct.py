"""The BubSub reconstruction pipeline: scan file in, one mesh per bubble out.

1. Low-resolution voxel reconstruction of the bubble data (FBP in 2D, FDK in 3D).
2. Bubble centres: Laplacian-of-Gaussian blobs or distance-transform maxima of the
   Otsu mask, in 2D whichever explains the data better (:mod:`.initial`).
3. One spherical control mesh per bubble with a constant radius, optionally
   improved by a radius-only fit (paper eq. 4-5), or a user-given initial mesh.
4. BFGS on all control vertices, coarse to fine in the data: binned pixels
   first, the full detector last, each level ended on convergence
   (:mod:`bubsub.clients.optimise.levels`); topology rounds (:mod:`.topology`)
   and the validity check and repair (:mod:`.repair`), each refitting only the
   bubbles it changed on detector windows (:mod:`.local`); one coarse-to-fine
   step in the control meshes, kept when it explains the data better
   (:mod:`.refine`), and its check and repair. A tall parallel-beam scan is
   reconstructed slab by slab of detector rows (:mod:`.slabs`).
5. Outputs, each written atomically: ``bubbles.ply`` (3D) or ``bubbles.json``
   (2D), ``bubbles.csv`` (+ ``bubbles.csv-metadata.json``), ``report.json``,
   ``overlay.png``, ``sizes.png`` and (3D) ``meshes.png``
   (:mod:`bubsub.clients.pipeline.figures`).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bubsub.core import MeshProjector, ScanGeometry
from bubsub.core.io.atomic import atomic_path
from bubsub.core.io.meshio import (BUBBLE_COLUMN_INFO, BUBBLE_COLUMNS_2D, BUBBLE_COLUMNS_3D, bubble_table,
                                   csv_metadata_path, read_ply, read_polygons_json, write_csv, write_ply,
                                   write_polygons_json)
from bubsub.core.metrics import projection_mse
from bubsub.core.projection.subdivision import SubdivisionSurface

from bubsub.clients.optimise.fit import estimate_radii
from bubsub.clients.optimise.levels import bin_factors, fit_levels
from bubsub.clients.pipeline.checks import check_bubble_signal, check_settings
from bubsub.clients.pipeline.fov import (FOV_COLUMN_INFO, field_of_view, fov_columns, fov_report, preview_extension,
                                         truncated_flags, unobserved_control)
from bubsub.clients.pipeline.initial import choose_initial, default_detector, initial_centres, initial_surfaces
from bubsub.clients.pipeline.outputs import finish_outputs, json_default
from bubsub.clients.pipeline.refine import can_refine, refine_and_check
from bubsub.clients.pipeline.repair import check_and_repair, merged_validity
from bubsub.clients.progress import phase
from bubsub.clients.pipeline.topology import adapt_bubbles

__all__ = ["ReconstructionSettings", "Reconstruction", "reconstruct", "field_of_view", "truncated_flags",
           "initial_centres", "initial_surfaces", "voxel_preview", "preview_grid", "resample_image"]


@dataclass
class ReconstructionSettings:
    """What ``bubsub reconstruct`` can be told (defaults follow the paper)."""

    iterations: int = 80  # each data level's cap (.optimise.levels); a level ends earlier on convergence
    data_levels: int | None = None  # fit on 2^(k-1)-binned, ..., full pixels; default 2 for 3D detectors >= 96 px
    fit_rtol: float | None = 2e-4  # converged: objective down by < fit_rtol x itself over 5 iterations
    control_points: int | None = None  # 42 in 3D, 9 in 2D
    levels: int = 2
    radius: float | None = None  # initial radius (mm); default: median from the distance transform
    estimate_radii: bool = True
    supersampling: int = 1
    holdout: str | None = None  # "odd" or "even": projections kept aside for validation
    voxel_size: float | None = None  # of the initial voxel reconstruction; default: from the field of view
    min_distance: float | None = None  # between bubble centres (mm)
    background_subtracted: bool = False  # accept a positive contrast without /exchange/background
    progress: bool = True
    preview: str = "box"  # voxel preview: "box" (0 <= x <= |contrast|, BB steps) or "sirt" (x >= 0)
    detector: str | None = None  # initial centres: "auto", "log" or "dt" (see .initial); default "auto" in 2D, "dt" in 3D
    topology: bool = True  # add/remove/merge/split bubbles between fits when the objective says so (see .topology)
    topology_rounds: int = 2
    repair: bool = True  # round self-intersecting bubbles, separate overlapping ones, refit (see .repair)
    repair_iterations: int = 20  # BFGS iterations of each refit after a repair
    fov_model: bool = False  # preview beyond the field of view, cut bubbles seeded at their edge (see .fov)
    # strength of the penalty keeping bubbles a film apart during the fits (.optimise.separation); off by
    # default: at 1 the dense 2D foam's DDI went from 0.010 to 0.077 (docs/robustness.md)
    separation: float = 0.0
    # coarse-to-fine: after the repair, refine each control mesh once and refit (then check and repair
    # again); kept when the Akaike score improves (.refine; bubbles from the preview only, not from --init)
    refine: bool = True
    refine_iterations: int = 80  # of the refined fit (it stops after 10 unless the refinement pays for itself)


@dataclass
class Reconstruction:
    """Result of :func:`reconstruct`."""

    surfaces: list
    report: dict
    preview: np.ndarray | None = None
    preview_extent: tuple | None = None
    files: dict = field(default_factory=dict)
    ids: list | None = None  # bubble ids written to the outputs (default 0..n-1); track ids in 4D


def preview_voxel_size(geometry):
    """Default voxel size of the preview (mm): the field of view over 256 (2D) or 160 (3D) voxels."""
    return 2 * field_of_view(geometry)[0] / (160 if geometry.ndim == 3 else 256)


def preview_grid(geometry, voxel_size=None, extend=1.0):
    """Shape and extent (mm) of the voxel preview's grid: the field of view at ``voxel_size`` (default
    :func:`preview_voxel_size`), its radius times ``extend`` (:func:`bubsub.clients.pipeline.fov.preview_extension`)."""
    r_xy, half_z = field_of_view(geometry)
    if voxel_size is None:
        voxel_size = preview_voxel_size(geometry)
    n = max(8, int(np.ceil(2 * extend * r_xy / voxel_size)))
    half = n * voxel_size / 2
    if geometry.ndim == 2:
        return (n, n), (-half, half, -half, half)
    nz = max(4, int(np.ceil(2 * half_z / voxel_size)))
    hz = nz * voxel_size / 2
    return (nz, n, n), (-half, half, -half, half, -hz, hz)


PREVIEW_FINE_ITERATIONS_3D = 5  # of the 3D preview's iterations, those on the requested grid (the rest on a 2x coarser one)


def voxel_preview(data, geometry, contrast, voxel_size=None, iterations=None, *, progress=False, method="box",
                  coarse_3d=True, extend=1.0):
    """Low-resolution voxel reconstruction of the bubbles, for the initialisation.

    The bubble data ``sign(contrast) * data`` is the projection of an image
    that is ``|contrast|`` inside bubbles and 0 elsewhere. ``method="box"``
    (default) uses both bounds: projected gradient descent with
    Barzilai-Borwein steps (:func:`bubsub.core.voxel.solvers.pgd_bb`) onto
    ``0 <= x <= |contrast|`` (50 iterations in 2D, 30 in 3D); at few views it
    separates touching bubbles that SIRT blurs together (README example, 13
    views: 37 of 40 bubbles found instead of 28; docs/robustness.md).
    ``method="sirt"``: SIRT with ``x >= 0`` only (100 iterations in 2D, 15 in 3D).
    ``extend`` widens the grid beyond the field of view's radius by that
    factor (:func:`bubsub.clients.pipeline.fov.preview_extension`), so that
    bubbles partly outside the reconstructable cylinder, which some
    projections see, have voxels to go to.

    Returns
    -------
    image : ndarray float32, ``(rows, cols)`` or ``(slices, rows, cols)``
        Bubble "density" (``|contrast|`` inside bubbles, 0 elsewhere).
    extent : tuple
        ``(xmin, xmax, ymin, ymax[, zmin, zmax])`` in mm.
    """
    if method not in ("box", "sirt"):
        raise ValueError(f"preview method must be 'box' or 'sirt', got {method!r}")
    shape, extent = preview_grid(geometry, voxel_size, extend)
    positive = np.sign(contrast) * np.asarray(data, dtype=np.float32)
    upper = np.float32(abs(contrast))
    box = method == "box"
    if geometry.ndim == 2 and not box:  # ASTRA's own SIRT: about a second, no per-iteration callback
        from bubsub.core.voxel.astra2d import reconstruct_2d

        with phase("voxel preview (2D SIRT)", 1, unit="reconstruction", enabled=progress) as bar:
            image = reconstruct_2d("sirt", positive, geometry, shape, extent, iterations=iterations or 100,
                                   nonneg=True)
            bar.update(1, voxels="x".join(map(str, shape)))
        return image, extent
    n = iterations or ((50 if box else 100) if geometry.ndim == 2 else (30 if box else 15))

    def step(k, x):
        if box:  # pgd_bb projects onto x >= 0 itself; this adds the upper bound to each iterate
            np.minimum(x, upper, out=x)
        bar.update(1)

    name = "bb" if box else "sirt"
    label = f"voxel preview ({geometry.ndim}D {'box-constrained BB' if box else 'SIRT'})"
    if geometry.ndim == 2:
        from bubsub.core.voxel.astra2d import reconstruct_2d

        with phase(label, n, enabled=progress) as bar:
            image = reconstruct_2d(name, positive, geometry, shape, extent, iterations=n, nonneg=True, callback=step)
            bar.postfix["voxels"] = "x".join(map(str, shape))
        return image, extent
    from bubsub.core.voxel.reconstruct3d import reconstruct_3d

    # Coarse to fine: the iterations run on voxels twice as large (8x fewer, so 8x
    # cheaper: the 3D preview was half of a reconstruction's time), then a few on
    # the requested grid refine the edges from there.
    fine = min(n, PREVIEW_FINE_ITERATIONS_3D)
    coarse = n - fine if coarse_3d else 0
    x0 = None
    with phase(label, n, enabled=progress) as bar:
        if coarse > 0:
            voxel = (extent[1] - extent[0]) / shape[-1]
            shape_c, extent_c = preview_grid(geometry, 2 * voxel, extend)
            image_c = reconstruct_3d(name, positive, geometry, shape_c, extent_c, iterations=coarse, nonneg=True,
                                     callback=step)
            x0 = resample_image(image_c, extent_c, shape, extent)
        image = reconstruct_3d(name, positive, geometry, shape, extent, iterations=n - coarse, nonneg=True, x0=x0,
                               callback=step)
        bar.postfix["voxels"] = "x".join(map(str, shape))
    return image, extent


def resample_image(image, extent, shape, new_extent):
    """Trilinear (bilinear in 2D) resampling of a voxel image onto another grid (edge values extended).

    Parameters
    ----------
    image : ndarray, ``(rows, cols)`` or ``(slices, rows, cols)``
    extent : tuple
        Of ``image``, mm (grid convention of :mod:`bubsub.core.voxel.grid`).
    shape, new_extent
        The new grid.

    Returns
    -------
    ndarray float32 of ``shape``
    """
    from scipy import ndimage

    from bubsub.core.voxel.grid import index_to_world, world_to_index

    # both grids are axis-aligned, so each new index maps to an old one by a per-axis affine
    # function: found from indices 0 and 1, applied without any coordinate arrays
    nd = len(shape)
    src = world_to_index(index_to_world(np.array([np.zeros(nd), np.ones(nd)]), shape, new_extent), image.shape, extent)
    out = ndimage.affine_transform(np.asarray(image, dtype=np.float32), src[1] - src[0], offset=src[0],
                                   output_shape=tuple(shape), order=1, mode="nearest")
    return out.astype(np.float32, copy=False)


def load_initial(path, contrast, levels=2):
    """Initial control meshes from a previous reconstruction (``bubbles.ply`` or ``bubbles.json``)."""
    path = Path(path)
    if path.suffix.lower() == ".ply":
        items = read_ply(path, attenuation=contrast)
    elif path.suffix.lower() == ".json":
        items = read_polygons_json(path, attenuation=contrast)
    else:
        raise ValueError(f"initial mesh {path} must be a .ply (3D) or .json (2D) file")
    return [SubdivisionSurface(m, levels) for m in items]


def _split(geometry, data, holdout):
    if holdout is None:
        return geometry, data, None, None
    if holdout not in ("odd", "even"):
        raise ValueError(f"holdout must be 'odd' or 'even', got {holdout!r}")
    keep = slice(0, None, 2) if holdout == "odd" else slice(1, None, 2)
    rest = slice(1, None, 2) if holdout == "odd" else slice(0, None, 2)
    if geometry.n_angles < 2:
        raise ValueError("holding out projections needs at least two of them")
    return geometry[keep], data[keep], geometry[rest], data[rest]


def reconstruct(scan, settings=None, *, init=None, projector_factory=None):
    """Reconstruct the bubbles of a scan.

    Parameters
    ----------
    scan : bubsub.core.io.scanfile.Scan
    settings : ReconstructionSettings, optional
    init : list of SubdivisionSurface, optional
        Initial bubbles (e.g. :func:`load_initial` of a previous frame);
        skips the voxel-based initialisation.
    projector_factory : callable(geometry, data, surfaces) -> projector, optional
        Makes the object :func:`fit` calls, holding ``data``; by default a
        local :class:`MeshProjector`. ``bubsub reconstruct --server`` passes
        one that creates a remote job with the surfaces' topology.

    Returns
    -------
    Reconstruction
    """
    s = settings or ReconstructionSettings()
    check_settings(s, scan.ndim)
    check_bubble_signal(scan, background_subtracted=s.background_subtracted)
    t0 = time.perf_counter()
    clock = _PhaseClock()
    contrast = scan.bubble_contrast
    data = scan.bubble_data
    geometry = scan.geometry
    g_fit, d_fit, g_val, d_val = _split(geometry, data, s.holdout)

    image, extent = voxel_preview(d_fit, g_fit, contrast, s.voxel_size, progress=s.progress, method=s.preview,
                                  extend=preview_extension(s.fov_model))
    clock.mark("preview")
    local = MeshProjector(g_fit, supersampling=s.supersampling)
    detector, initialisation = default_detector(s.detector, g_fit.ndim), None
    if init is None:
        # "auto" compares the candidate sets after their radius-only fits, here (a local projector)
        surfaces, initialisation = choose_initial(
            image, extent, contrast, local, d_fit, detector=detector, estimate=s.estimate_radii and detector == "auto",
            progress=s.progress, control_points=s.control_points, levels=s.levels, radius=s.radius,
            min_distance=s.min_distance, border_is_background=not s.fov_model)
    else:
        surfaces = [x.with_attenuation(contrast) for x in init]
    if projector_factory is None:
        projector, fit_data = local, d_fit
    else:
        projector = projector_factory(g_fit, d_fit, surfaces)
        fit_data = None
    t_init = time.perf_counter() - t0
    clock.mark("initial_bubbles")
    factors = bin_factors(g_fit, s.data_levels)
    if s.estimate_radii and init is None and detector != "auto":
        # on the coarsest level's pixels: the radii need not see every pixel
        coarse = MeshProjector(g_fit.binned(factors[0]), supersampling=s.supersampling)
        surfaces = estimate_radii(coarse, surfaces, ScanGeometry.bin_projections(d_fit, factors[0]),
                                  progress=s.progress)
    clock.mark("radius_estimation")
    voxel = (extent[1] - extent[0]) / image.shape[-1]
    penalty = _separation(s, d_fit, len(surfaces), voxel) if fit_data is not None else None
    # the objective of the initial bubbles on the full detector (the levels' own objectives are on their pixels)
    f_start = float((projector.objective(surfaces, fit_data) if fit_data is not None
                     else projector.objective(surfaces))[0])
    result, fit_levels_report = fit_levels(projector, surfaces, d_fit, factors=factors, iterations=s.iterations,
                                           rtol=s.fit_rtol, penalty=penalty, progress=s.progress,
                                           factory=projector_factory)
    clock.mark("fit")
    kept, dropped = prune(result.surfaces, min_radius=voxel)
    topology = refinement = None
    interrupted = result.interrupted  # Ctrl-C: no further changes, write what we have
    checker = local
    try:
        if s.topology and s.topology_rounds > 0 and kept and not interrupted:
            kept, topology = adapt_bubbles(kept, g_fit, d_fit, contrast, image, extent, voxel, s, penalty=penalty)
        clock.mark("topology")

        def checked(items):
            return check_and_repair(items, checker, d_fit, repair=s.repair and not interrupted,
                                    iterations=s.repair_iterations, gap=0.25 * voxel, penalty=penalty)

        kept, validity = checked(kept)
        clock.mark("validity")
        if s.refine and init is None and can_refine(kept) and not interrupted:
            # after the repair, so the refined fit also fills the gas of dropped bubbles; checked again
            kept, refinement, again = refine_and_check(local, kept, d_fit, checked, iterations=s.refine_iterations,
                                                       penalty=penalty, progress=s.progress, rtol=s.fit_rtol)
            if again is not None:
                validity = merged_validity(validity, again)
        clock.mark("refine")
    except KeyboardInterrupt:  # in the topology rounds, the repair or the refinement: report the bubbles as they were
        interrupted = True
        kept, validity = check_and_repair(kept, checker, d_fit, repair=False)
        clock.mark("validity")

    report = {
        "bubbles": len(kept),
        "bubbles_initial": len(surfaces),
        "initialisation": initialisation,
        "bubbles_dropped": dropped + validity["dropped"],
        "validity": validity,
        "topology": topology,
        "refinement": refinement,
        "dimension": geometry.ndim,
        "iterations": result.iterations,
        "evaluations": result.evaluations,
        "fit_levels": fit_levels_report,
        "final_objective": result.objective,
        "initial_objective": f_start,
        "method": result.method,
        "interrupted": interrupted,
        "stop_reason": "interrupted" if interrupted else result.stop_reason,
        "seconds_total": time.perf_counter() - t0,
        "seconds_fit": result.seconds,
        "seconds_initialisation": t_init,
        "projections_used": g_fit.n_angles,
        "holdout": s.holdout,
        "field_of_view_mm": fov_report(geometry),
        "unobserved_control_vertices": [int(unobserved_control(x, g_fit).sum()) for x in kept],
        "settings": {k: v for k, v in s.__dict__.items() if k != "progress"},
    }
    if g_val is not None:
        pred = MeshProjector(g_val, supersampling=s.supersampling).forward(kept)
        report["holdout_projections"] = g_val.n_angles
        report["holdout_mse"] = projection_mse(pred, d_val)
        clock.mark("holdout")
    # wall and CPU seconds of each phase (CPU: this process, all threads)
    report["seconds_parts"], report["cpu_seconds_parts"] = clock.parts()
    return Reconstruction(kept, report, image, extent)


def _separation(settings, data, n_bubbles, voxel):
    """The fit's separation penalty (:mod:`bubsub.clients.optimise.separation`), or None when switched off."""
    if not settings.separation:
        return None
    from functools import partial

    from bubsub.clients.optimise.separation import separation_penalty, separation_weight

    return partial(separation_penalty, weight=separation_weight(data, n_bubbles, voxel, settings.separation),
                   gap=0.25 * voxel)


class _PhaseClock:
    """Wall and CPU seconds (this process, all threads) of consecutive phases, for ``report.json``."""

    def __init__(self):
        self._wall, self._cpu = time.perf_counter(), time.process_time()
        self._parts = {}

    def mark(self, name):
        """End the phase ``name`` now; the next one starts."""
        wall, cpu = time.perf_counter(), time.process_time()
        self._parts[name] = (wall - self._wall, cpu - self._cpu)
        self._wall, self._cpu = wall, cpu

    def parts(self):
        """``({phase: wall seconds}, {phase: CPU seconds})``."""
        return {k: w for k, (w, _) in self._parts.items()}, {k: c for k, (_, c) in self._parts.items()}


def prune(surfaces, min_radius):
    """Drop bubbles the fit collapsed or turned inside out (spurious initial centres).

    A bubble stays when its subdivided surface encloses a positive area
    (volume) of at least that of a disc (ball) of ``min_radius``.

    Returns
    -------
    kept : list of SubdivisionSurface
    dropped : int
    """
    kept = []
    for s in surfaces:
        fine = s.fine()
        size = fine.volume if s.ndim == 3 else fine.area
        least = 4 / 3 * np.pi * min_radius**3 if s.ndim == 3 else np.pi * min_radius**2
        if size >= least:
            kept.append(s)
    return kept, len(surfaces) - len(kept)


def write_outputs(out_dir, rec, scan_path=None, *, progress=False):
    """Write ``bubbles.ply|json``, ``control.ply|json``, ``bubbles.csv`` and its column sidecar,
    ``report.json`` and the pictures of :func:`write_figures`.

    Every file goes to a temporary name first and is renamed when complete;
    then the files of an earlier run in ``out_dir`` that were not replaced are
    removed (:func:`bubsub.clients.pipeline.outputs.finish_outputs`). Callers
    that must not replace earlier results check the folder first
    (:func:`bubsub.clients.pipeline.outputs.check_output_folder`).
    ``progress`` shows the pictures as a phase (seconds for 3D meshes).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fine = [s.fine() for s in rec.surfaces]
    files = {}
    if rec.report["dimension"] == 3:
        files["mesh"] = out / "bubbles.ply"
        write_ply(files["mesh"], [s.fine() for s in rec.surfaces], rec.ids)
        files["control"] = out / "control.ply"
        write_ply(files["control"], [s.control for s in rec.surfaces], rec.ids)
    else:
        files["mesh"] = out / "bubbles.json"
        write_polygons_json(files["mesh"], fine, rec.ids)
        files["control"] = out / "control.json"
        write_polygons_json(files["control"], [s.control for s in rec.surfaces], rec.ids)
    files["table"] = out / "bubbles.csv"
    rows = bubble_table(fine, rec.ids)
    columns = BUBBLE_COLUMNS_3D if rec.report["dimension"] == 3 else BUBBLE_COLUMNS_2D
    info = BUBBLE_COLUMN_INFO
    if rec.report.get("field_of_view_mm") is not None and fine:
        # bubbles cut by the edge of the field of view are flagged, not dropped; their whole size is left empty
        columns = (*columns, *fov_columns(rows, fine, rec.report))
        info = {**info, **FOV_COLUMN_INFO}
    write_csv(files["table"], rows, columns,
              describe=info, title="bubbles reconstructed by bubsub reconstruct")
    files["table_columns"] = csv_metadata_path(files["table"])
    report = dict(rec.report)
    if scan_path is not None:
        report["scan"] = str(scan_path)
    files.update(write_figures(out, rec, fine, rows, progress=progress))
    report["files"] = {k: v.name for k, v in files.items()}
    files["report"] = out / "report.json"
    with atomic_path(files["report"]) as tmp:
        Path(tmp).write_text(json.dumps(report, indent=2, default=json_default))
    rec.files = files
    finish_outputs(out, files.values(), command="reconstruct")
    return files


def write_figures(out, rec, fine, rows, *, progress=False):
    """``overlay.png`` (preview slices with outlines), ``sizes.png`` and, in 3D, ``meshes.png``."""
    from bubsub.clients.pipeline.figures import write_mesh_view, write_overlay, write_size_histogram

    out = Path(out)
    ids = [r["id"] for r in rows]
    files = {}
    three_d = rec.report["dimension"] == 3
    total = 1 + (rec.preview is not None) + three_d
    with phase("pictures", total, unit="picture", enabled=progress) as bar:
        if rec.preview is not None:
            files["overlay"] = out / "overlay.png"
            write_overlay(files["overlay"], rec.preview, rec.preview_extent, fine, ids)
            bar.update()
        files["sizes"] = out / "sizes.png"
        write_size_histogram(files["sizes"], [r["equivalent_diameter_mm"] for r in rows
                                              if r["equivalent_diameter_mm"] != ""], rec.report["dimension"])
        bar.update()
        if three_d:
            # mplot3d draws every face: very many bubbles are shown by their control meshes
            shown = fine if sum(len(m.faces) for m in fine) <= 60000 else [s.control for s in rec.surfaces]
            files["meshes"] = out / "meshes.png"
            write_mesh_view(files["meshes"], shown, ids)
            bar.update()
    return files
