"""``python -m bubsub.bench fov``'s local-tomography cases: raw beamline scans of a foam wider than the detector,
or of a liquid cylinder just inside it, prepared and reconstructed, scored in the interior.

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

``python -m bubsub.bench fov --local 0 1 2 [--local-center auto|given] [--local-radius fitted|given|exact] [--out DIR]``

``--local-passes N`` sets the refits of the detector's view-constant term (0: none), ``--local-term
eliminated|alternated`` how it is fitted, and ``--local-contrast prepared`` keeps the prepared contrast where the
default estimates it again once the term is out, ``--local-final-refit off`` leaves out the last refit of every
bubble with the term eliminated (:mod:`bubsub.clients.pipeline.static.detector_term`), ``--local-double-flat off``
prepares without dividing out the pixel gains that the flats do not show (:mod:`bubsub.core.prep.gains`).

``--local-foam large|small|wide`` varies the foam (:data:`LOCAL_FOAMS`: bubbles of 0.15-0.25 of the field of
view's radius, of 0.05-0.09, or the liquid twice the field of view's radius, as densely filled).
``--local-reach R`` sets the field-of-view radii beyond which ``prepare`` takes the foam into the background
(:func:`bubsub.core.prep.background.foam_beyond`; ``inf``: the liquid alone, the alternative measured).

``python -m bubsub.bench fov --local 0 1 2 3 4 5 6 7 8 9 --local-foam large [--local-reach inf]``

``--local-radius given`` passes the liquid cylinder's radius (``bubsub prepare --liquid-radius``, the container's
inner radius a beamline user knows) instead of fitting it; ``--local-radius exact`` reconstructs with the exact
background (the liquid's exact projection and the true bubbles' mean projection beyond the reach) and the true
contrast (what the reconstruction reaches with a perfect background).

``--local-background SEED ...``: the background alone (:func:`local_background_case`): the liquid's projection
that :func:`bubsub.core.prep.background.chord_background` fits to the prepared scan's row, its radius fitted,
given, or given 5 % off, against the liquid's exact projection.

``python -m bubsub.bench fov --local-background 0 1 2 3 4 5 6 7``

``--local-ideal SEED ... --local-extend 1.25 1.6``: the reconstruction side
alone on exact projections of such a foam with its liquid's exact projection
as background (:func:`local_ideal_case`), the preview's radius for a foam
wider than the detector varied (the design's alternative: every bubble of
the foam in the model).

``python -m bubsub.bench fov --local-ideal 0 --local-extend 1.25 1.6``

``--local-axis SEED ...``: the axis alone (:func:`local_axis_case`): the raw scan of ``--local`` simulated and
prepared with ``--center auto`` (no background, no reconstruction), the axis found against the true one.

``python -m bubsub.bench fov --local-axis 0 1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 16 17 18 19 [--out DIR]``

``--inside SEED ...``: a raw scan whose liquid cylinder stands just inside the detector
(:func:`inside_case`), through the same preparation and reconstruction, scored by ``bubsub evaluate``.

``python -m bubsub.bench fov --inside 0 1 2 [--out DIR]``
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from bubsub.clients.pipeline.inputs import fov as fovmod
from bubsub.clients.pipeline.evaluation.evaluate import evaluate_dir
from bubsub.clients.pipeline.inputs.fov import field_of_view
from bubsub.clients.pipeline.results.outputs import write_outputs
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, reconstruct
from bubsub.clients.pipeline.static import detector_term as dtmod
from bubsub.clients.pipeline.static.detector_term import (CONTRAST_AGAIN, DETECTOR_TERM_METHOD, DETECTOR_TERM_PASSES,
                                                          FINAL_REFIT)
from bubsub.core import MeshProjector
from bubsub.core.foam.raw import disc_foam, raw_settings, write_raw_simulation
from bubsub.core.io.meshio import read_polygons_json
from bubsub.core.io.scanfile import Scan, read_scan
from bubsub.core.matching import match
from bubsub.core.metrics import dice_dissimilarity
from bubsub.core.prep import prepare, prepare_options
from bubsub.core.prep import background as bgmod
from bubsub.bench.local_truth import true_background, truth_gas
from bubsub.core.prep.background import chord_background, detector_offsets, foam_beyond
from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.projection.mesh import Polygon
from bubsub.core.projection.masks import label_image

__all__ = ["LOCAL_SCAN", "INSIDE_SCAN", "INSIDE_MARGIN", "inside_case", "local_case", "local_ideal_case",
           "local_background_case", "local_axis_case", "interior_scores", "print_local", "print_inside", "print_local_ideal",
           "print_local_background", "print_local_axis"]


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
    ``bubsub evaluate`` (:func:`bubsub.clients.pipeline.evaluation.evaluate.evaluate_dir`).

    Returns
    -------
    dict
        ``ddi``, ``truth``, ``found``, ``spurious``, ``reconstructed``, ``axis_error_px`` (raw pixels),
        ``contrast`` (1/mm), ``prepare_s``, ``reconstruct_s``.
    """
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


#: The foams of the local-tomography case (``--local-foam``): the bubbles' mean radii as fractions of the field of
#: view's radius, the bubbles placed in the liquid's bounding square (those not wholly inside the liquid dropped),
#: and the liquid cylinder's radius over the field of view's. ``standard`` is the case of the module docstring;
#: ``large`` (a coarsened foam, a few bubbles across the field of view), ``small`` (bubbles of 3-5.5 binned pixels'
#: radius) and ``wide`` (the liquid twice the field of view, as densely filled) vary it.
LOCAL_FOAMS = {"standard": ((0.08, 0.15), 80, 1.5), "large": ((0.15, 0.25), 30, 1.5),
               "small": ((0.05, 0.09), 220, 1.5), "wide": ((0.08, 0.15), 142, 2.0)}


def _local_raw(out, seed, foam="standard"):
    """Write the local-tomography case's raw simulation of ``seed`` and ``foam`` (:data:`LOCAL_FOAMS`) under
    ``out``: its :class:`RawSettings`."""
    if foam not in LOCAL_FOAMS:
        raise ValueError(f"foam must be one of {sorted(LOCAL_FOAMS)}, got {foam!r}")
    (small, large), placed, wider = LOCAL_FOAMS[foam]
    c = LOCAL_SCAN
    axis = c["cols"] / 2 - 0.5 + c["axis_offset"]
    half = min(axis + 0.5, c["cols"] - 0.5 - axis) * c["pixel_size"]
    radius = wider * half
    s = raw_settings(seed=seed, container_radius=radius, wall=0.0, wider_than_detector=True, **c)
    write_raw_simulation(out, disc_foam(seed, radius, n_bubbles=placed, radius_range=(small * half, large * half)), s)
    return s


def local_case(out, seed, *, center="auto", radius="fitted", passes=DETECTOR_TERM_PASSES, term=DETECTOR_TERM_METHOD,
               contrast_again=CONTRAST_AGAIN, foam="standard", reach=None, final_refit=FINAL_REFIT, double_flat="auto"):
    """Simulate, prepare, reconstruct and score one local-tomography scan (see the module docstring).

    ``passes``, ``term``, ``contrast_again`` and ``final_refit``: the refits of the detector's view-constant term,
    how it is fitted, whether the contrast is estimated again without it, and whether every bubble is refitted
    with it eliminated last (:data:`~bubsub.clients.pipeline.static.detector_term.DETECTOR_TERM_PASSES`, 0: none;
    :data:`~bubsub.clients.pipeline.static.detector_term.DETECTOR_TERM_METHOD`,
    :data:`~bubsub.clients.pipeline.static.detector_term.CONTRAST_AGAIN`,
    :data:`~bubsub.clients.pipeline.static.detector_term.FINAL_REFIT`).

    ``double_flat``: ``prepare``'s (``auto``, ``on``, ``off``; :mod:`bubsub.core.prep.gains`).

    ``foam``: :data:`LOCAL_FOAMS`. ``reach``: the field-of-view radii beyond which ``prepare`` takes the foam into
    the background (:data:`~bubsub.core.prep.background.FOAM_BEYOND_REACH` unless given; ``inf``: the liquid
    alone).

    ``radius="given"`` passes the liquid cylinder's true radius to ``prepare`` (``liquid_radius``);
    ``radius="exact"`` reconstructs the prepared data with the exact background (the liquid's exact projection and
    the true bubbles' mean projection beyond ``reach``, :func:`~bubsub.bench.local_truth.true_background`) and the
    true contrast instead of the fitted ones (the reconstruction's share of the error).

    Returns
    -------
    dict
        :func:`interior_scores` and ``axis_error_px`` (raw pixels), ``center`` (the method or the error),
        ``contrast`` (prepared, 1/mm), ``contrast_fitted`` (the bubbles', estimated again without the detector
        term by default), ``prepare_s``, ``reconstruct_s``; ``failed`` with the message where prepare stops.
    """
    out = Path(out)
    s = _local_raw(out, seed, foam)
    t0 = time.perf_counter()
    default_reach = bgmod.FOAM_BEYOND_REACH
    bgmod.FOAM_BEYOND_REACH = default_reach if reach is None else reach
    try:
        report = prepare(out / "raw.h5", out / "scan.h5", prepare_options(
            roi="1:2,:", bin=2, delta_beta=1450, center="auto" if center == "auto" else s.axis_column,
            background="auto", liquid_radius=s.container_radius if radius == "given" else None,
            double_flat=double_flat), progress=False)
    except ValueError as exc:
        return {"failed": str(exc), "prepare_s": time.perf_counter() - t0}
    finally:
        bgmod.FOAM_BEYOND_REACH = default_reach
    t1 = time.perf_counter()
    step = next(x for x in report["steps"] if x["step"] == "center")
    scan = read_scan(out / "scan.h5")
    if radius == "exact":
        exact = sum(true_background(out, s, detector_offsets(scan.geometry), reach=reach))
        scan = dataclasses.replace(scan, background=np.broadcast_to(exact, scan.data.shape).astype(np.float32),
                                   bubble_contrast=-s.liquid_mu)  # gas: no attenuation
    names = ("DETECTOR_TERM_PASSES", "DETECTOR_TERM_METHOD", "CONTRAST_AGAIN", "FINAL_REFIT")
    before = [getattr(dtmod, name) for name in names]
    for name, value in zip(names, (passes, term, contrast_again, final_refit)):
        setattr(dtmod, name, value)
    try:
        rec = reconstruct(scan, ReconstructionSettings(progress=False))
    finally:
        for name, value in zip(names, before):
            setattr(dtmod, name, value)
    t2 = time.perf_counter()
    scores = interior_scores([x.fine() for x in rec.surfaces], read_polygons_json(out / "truth.json"), scan.geometry)
    contrast = scan.bubble_contrast  # prepare's estimate, or the truth with radius="exact"
    fitted = rec.report.get("detector_term", {}).get("contrast_per_mm", contrast)  # estimated again
    return {**scores, "axis_error_px": step["axis_column_raw"] - s.axis_column, "center": step["method"],
            "contrast": contrast, "contrast_fitted": fitted, "prepare_s": t1 - t0, "reconstruct_s": t2 - t1}


def local_axis_case(out, seed):
    """The local-tomography case's axis alone: ``bubsub prepare --bin 2 --delta-beta 1450 --center auto``.

    The raw scan of :func:`local_case` (its true axis known to the
    simulation), prepared without a background (the axis is found before
    it) and not reconstructed.

    Returns
    -------
    dict
        ``true`` and ``found`` (raw detector columns), ``error_px`` (found less true, raw pixels), ``method``
        (the report's), ``prepare_s`` (CPU seconds); ``failed`` with the message where prepare stops.
    """
    out = Path(out)
    s = _local_raw(out, seed)
    t0 = time.process_time()
    try:
        report = prepare(out / "raw.h5", out / "scan.h5", prepare_options(
            roi="1:2,:", bin=2, delta_beta=1450, center="auto", background="none"), progress=False)
    except ValueError as exc:
        return {"true": s.axis_column, "failed": str(exc), "prepare_s": time.process_time() - t0}
    step = next(x for x in report["steps"] if x["step"] == "center")
    return {"true": s.axis_column, "found": step["axis_column_raw"], "error_px": step["axis_column_raw"] - s.axis_column,
            "method": step["method"], "prepare_s": time.process_time() - t0}


def local_background_case(out, seed, foam="standard", double_flat="auto"):
    """The local-tomography case's background alone, against the liquid's exact projection.

    The raw scan of :func:`local_case` prepared as there but with the true
    axis and without a background (the phase-retrieved line integrals of
    its row, which ``--background auto`` fits), and
    :func:`bubsub.core.prep.background.chord_background` run on it with the
    liquid's radius fitted, given, and given 5 % small or large; each
    against the liquid's exact projection ``mu 2 sqrt(R^2 - s^2)``.
    ``double_flat``: ``prepare``'s.

    Returns
    -------
    dict
        ``true_radius_mm``, ``inner_gas_fraction`` and ``outer_gas_fraction``
        (the truth bubbles' area fractions inside the field of view's disc
        and between it and the liquid's wall), and ``fits``: per radius
        (``fitted``, ``given``, ``given x0.95``, ``given x1.05``) the fit
        (:func:`~bubsub.core.prep.background.chord_background`'s dict),
        ``axis_error`` (the background less the liquid's projection at the
        axis) and ``shape_error`` (that error's mean at the two outermost
        columns less its value at the axis: the curvature that a constant
        offset leaves out).
    """
    out = Path(out)
    s = _local_raw(out, seed, foam)
    prepare(out / "raw.h5", out / "scan.h5", prepare_options(
        roi="1:2,:", bin=2, delta_beta=1450, center=s.axis_column, background="none", double_flat=double_flat),
        progress=False)
    scan = read_scan(out / "scan.h5")
    sino, geometry = scan.data, scan.geometry  # one row: 2D
    offsets = detector_offsets(geometry)
    r_true = s.container_radius
    axis = int(np.argmin(np.abs(offsets)))
    r_fov = float(min(-offsets[0], offsets[-1]))
    gas, r = truth_gas(out, s)
    liquid, beyond_true = true_background(out, s, offsets, (gas, r))

    def errors(err):
        return {"axis_error": float(err[axis]), "shape_error": float(0.5 * (err[0] + err[-1]) - err[axis])}

    fits = {}
    for name, radius in (("fitted", None), ("given", r_true), ("given x0.95", 0.95 * r_true),
                         ("given x1.05", 1.05 * r_true)):
        bg, fit = chord_background(sino, geometry, radius=radius)
        fits[name] = {"fit": fit, **errors(bg - liquid),
                      "with_foam_beyond": errors(bg + foam_beyond(fit, geometry) - liquid - beyond_true)}
    return {"true_radius_mm": r_true, "inner_gas_fraction": float(gas[r <= r_fov].mean()),
            "outer_gas_fraction": float(gas[(r > r_fov) & (r <= r_true)].mean()), "fits": fits}


def local_ideal_case(seed, extend):
    """The local-tomography foam on exact projections, its liquid's exact projection as background.

    90 parallel views over 180 degrees of a 128-column detector of 40 um
    pixels; a liquid disc 1.5 times the field of view's radius filled with
    bubbles (:func:`bubsub.core.foam.raw.disc_foam`), projected exactly
    (Gaussian noise 0.003), reconstructed with its defaults but the preview
    out to ``extend`` times the field of view's radius for a foam wider than
    the detector (:data:`bubsub.clients.pipeline.inputs.fov.LOCAL_EXTEND`): the
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


def _case_dir(kind, args, seed):
    """The folder of one case under ``args.out``: ``local3``, ``local-large3``, ``background3``..."""
    foam = getattr(args, "local_foam", "standard")
    return f"{kind}{seed}" if foam == "standard" else f"{kind}-{foam}{seed}"


def print_local(args):
    """Print the table of :func:`local_case` for ``args.local`` (seeds), ``args.local_center``, ``args.out``."""
    print(f"| seed | centre | axis error (raw px) | contrast (1/mm): prepared, fitted | interior bubbles "
          f"| found (IoU >= 0.5) | spurious | DDI (interior) | prepare s | reconstruct s |")
    print("|---|---|---|---|---|---|---|---|---|---|", flush=True)
    for seed in args.local:
        r = local_case(Path(args.out) / _case_dir("local", args, seed), seed, center=args.local_center,
                       radius=args.local_radius,
                       passes=getattr(args, "local_passes", DETECTOR_TERM_PASSES),
                       term=getattr(args, "local_term", DETECTOR_TERM_METHOD),
                       contrast_again=getattr(args, "local_contrast", "again") == "again",
                       foam=getattr(args, "local_foam", "standard"), reach=getattr(args, "local_reach", None),
                       final_refit=getattr(args, "local_final_refit", "on") == "on",
                       double_flat=getattr(args, "local_double_flat", "auto"))
        if "failed" in r:
            print(f"| {seed} | {args.local_center} | prepare stopped: {r['failed']} | | | | | | "
                  f"{r['prepare_s']:.0f} | |", flush=True)
            continue
        print(f"| {seed} | {args.local_center} | {r['axis_error_px']:+.2f} | {r['contrast']:.4f}, "
              f"{r['contrast_fitted']:.4f} | {r['truth']} | "
              f"{r['found']} ({r['found_percent']:.0f} %) | {r['spurious']} | {r['ddi']:.4f} | {r['prepare_s']:.0f} | "
              f"{r['reconstruct_s']:.0f} |", flush=True)
    return 0


def print_local_background(args):
    """Print the table of :func:`local_background_case` for ``args.local_background`` (seeds) under ``args.out``.

    One row per seed: the true gas fractions, then per radius (fitted, given, given 5 % small, 5 % large) the mean
    projection's residual (rms), the error at the axis and the shape error; the radius where fitted and the
    outer gas fraction where given; last, the axis and shape errors of the background that ``prepare`` writes (the
    liquid and the foam beyond :data:`~bubsub.core.prep.background.FOAM_BEYOND_REACH` field-of-view radii) against
    the liquid's exact projection and the true bubbles' mean projection beyond, the radius fitted and given.
    """
    print("| seed | true gas fraction inside / beyond | fitted: radius (mm), residual, axis, shape | given: gas "
          "beyond, residual, axis, shape | given x0.95: residual, axis, shape | given x1.05: residual, axis, shape "
          "| with the foam beyond, fitted: axis, shape | given: axis, shape |")
    print("|---|---|---|---|---|---|---|---|", flush=True)
    for seed in args.local_background:
        r = local_background_case(Path(args.out) / _case_dir("background", args, seed), seed,
                                  getattr(args, "local_foam", "standard"), getattr(args, "local_double_flat", "auto"))
        f = r["fits"]
        cell = lambda x: (f"{x['fit']['residual_rms']:.4f}, {x['axis_error']:+.4f}, {x['shape_error']:+.4f}")
        whole = lambda x: f"{x['with_foam_beyond']['axis_error']:+.4f}, {x['with_foam_beyond']['shape_error']:+.4f}"
        print(f"| {seed} | {r['inner_gas_fraction']:.2f} / {r['outer_gas_fraction']:.2f} | "
              f"{f['fitted']['fit']['radius_mm']:.2f}, {cell(f['fitted'])} | "
              f"{f['given']['fit']['outer_gas_fraction']:.2f}, {cell(f['given'])} | {cell(f['given x0.95'])} | "
              f"{cell(f['given x1.05'])} | {whole(f['fitted'])} | {whole(f['given'])} |", flush=True)
    return 0


def print_local_axis(args):
    """Print the table of :func:`local_axis_case` for ``args.local_axis`` (seeds) under ``args.out``, then the
    largest and the median absolute error."""
    print("| seed | true axis (raw column) | found | error (raw px) | method | prepare CPU s |")
    print("|---|---|---|---|---|---|", flush=True)
    errors = []
    for seed in args.local_axis:
        r = local_axis_case(Path(args.out) / f"axis{seed}", seed)
        if "failed" in r:
            print(f"| {seed} | {r['true']:.2f} | stopped | | {r['failed']} | {r['prepare_s']:.1f} |", flush=True)
            continue
        errors.append(abs(r["error_px"]))
        print(f"| {seed} | {r['true']:.2f} | {r['found']:.2f} | {r['error_px']:+.2f} | {r['method']} | "
              f"{r['prepare_s']:.1f} |", flush=True)
    if errors:
        print(f"\n{len(errors)} of {len(args.local_axis)} found; |error| largest {max(errors):.2f}, median "
              f"{float(np.median(errors)):.2f} raw px")
    return 0


def print_inside(args):
    """Print the table of :func:`inside_case` for ``args.inside`` (seeds) under ``args.out``."""
    print("| seed | axis error (raw px) | contrast (1/mm) | bubbles | found (IoU >= 0.5) | spurious | DDI | prepare s | "
          "reconstruct s |")
    print("|---|---|---|---|---|---|---|---|---|", flush=True)
    for seed in args.inside:
        r = inside_case(Path(args.out) / f"inside{seed}", seed)
        print(f"| {seed} | {r['axis_error_px']:+.2f} | {r['contrast']:.4f} | {r['truth']} | {r['found']} | "
              f"{r['spurious']} | {r['ddi']:.4f} | {r['prepare_s']:.0f} | {r['reconstruct_s']:.0f} |", flush=True)
    return 0


def print_local_ideal(args):
    """Print the table of :func:`local_ideal_case` for ``args.local_ideal`` (seeds) and ``args.local_extend``."""
    print("| seed | preview radius / field of view's | interior bubbles | found (IoU >= 0.5) | spurious | "
          "DDI (interior) | bubbles reconstructed | reconstruct s |")
    print("|---|---|---|---|---|---|---|---|", flush=True)
    for seed in args.local_ideal:
        for extend in args.local_extend:
            r = local_ideal_case(seed, extend)
            print(f"| {seed} | {extend:g} | {r['truth']} | {r['found']} ({r['found_percent']:.0f} %) | {r['spurious']} "
                  f"| {r['ddi']:.4f} | {r['reconstructed']} | {r['reconstruct_s']:.0f} |", flush=True)
    return 0
