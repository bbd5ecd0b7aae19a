"""Simulated scans on disk: a phantom, its scan geometry, ``scan.h5`` and the ground truth."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from bubsub.clients.pipeline.results.outputs import finish_outputs
from bubsub.core import ScanGeometry
from bubsub.core.foam import phantoms
from bubsub.core.foam.simulate import simulate_2d, simulate_3d
from bubsub.core.io.atomic import atomic_write_text
from bubsub.core.io.meshio import write_ply, write_polygons_json
from bubsub.core.io.scanfile import write_scan

__all__ = ["PHANTOMS", "DYNAMIC_PHANTOMS", "make_phantom", "make_geometry", "truth_grid", "simulate_to_dir",
           "simulate_dynamic_to_dir", "simulate_flowing_to_dir", "simulate_raw_to_dir"]

PHANTOMS = ("foam2d", "foam3d", "foam3d-benchmark")
#: Dynamic scans: expanding foams (:mod:`bubsub.core.foam.expanding`) and a flowing, coarsening foam column
#: (:mod:`bubsub.core.foam.flowing`).
DYNAMIC_PHANTOMS = ("expanding2d", "expanding3d", "flowing3d")


def make_phantom(name, seed, n_bubbles=None):
    if name == "foam2d":
        return phantoms.foam2d(seed, **({"n_bubbles": n_bubbles} if n_bubbles else {}))
    if name == "foam3d":
        return phantoms.foam3d(seed, **({"n_bubbles": n_bubbles} if n_bubbles else {}))
    if name == "foam3d-benchmark":
        return phantoms.foam3d_benchmark()
    raise ValueError(f"unknown phantom {name!r}; choose one of {PHANTOMS}")


def make_geometry(ndim, beam, n_angles, det_count=None, rows=None, repeat=1):
    """The scans of the paper: 2D parallel over [0, pi), 3D cone over [0, 2 pi).

    ``repeat`` rotations of ``n_angles`` each, in acquisition order (a dynamic scan's subscans).
    """
    def circle(period):
        return np.tile(np.linspace(0, period, n_angles, endpoint=False), int(repeat))

    if ndim == 2:
        # a 14.4 mm detector sees the whole 10 mm square at every angle
        cols = det_count or 2400
        if beam == "parallel":
            return ScanGeometry.parallel(circle(np.pi), pixel_size=14.4 / cols, cols=cols)
        angles = circle(2 * np.pi)
        return ScanGeometry.cone(angles, source_origin=300.0, origin_detector=15.0, pixel_size=15.2 / cols, cols=cols)
    cols = det_count or 512
    rows = rows or cols // 2
    pixel = 0.06 * 512 / cols
    if beam == "parallel":
        return ScanGeometry.parallel(circle(np.pi), pixel_size=pixel, cols=cols, rows=rows)
    angles = circle(2 * np.pi)
    return ScanGeometry.cone(angles, source_origin=300.0, origin_detector=15.0, pixel_size=pixel, cols=cols, rows=rows)


def truth_grid(phantom, resolution=None):
    """The grid ground truth and reconstructions are compared on (shape, extent)."""
    if phantom.ndim == 2:
        return phantom.grid(resolution or 1000)
    size = np.asarray(phantom.size)
    voxel = resolution or 0.1
    shape = tuple(int(round(s / voxel)) for s in size[::-1])  # (z, y, x)
    return phantom.grid(shape)


def simulate_to_dir(out, phantom_name="foam2d", *, angles=25, photons=1e4, seed=0, beam=None,
                    det_count=None, n_bubbles=None, method="voxel"):
    """Simulate a scan and write ``scan.h5``, ``truth.json|ply`` and ``phantom.json`` to ``out``.

    The files of an earlier run in ``out`` that are not replaced are removed
    (:func:`bubsub.clients.pipeline.results.outputs.finish_outputs`); ``bubsub
    simulate`` first refuses a folder with earlier results unless ``--overwrite``.
    """

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    phantom = make_phantom(phantom_name, seed, n_bubbles)
    beam = beam or ("parallel" if phantom.ndim == 2 else "cone")
    geometry = make_geometry(phantom.ndim, beam, angles, det_count)
    if phantom.ndim == 2:
        scan = simulate_2d(phantom, geometry, photons=photons, seed=seed, method=method)
        truth = out / "truth.json"
        write_polygons_json(truth, phantom.bubbles)
    else:
        scan = simulate_3d(phantom, geometry, photons=photons, seed=seed)
        truth = out / "truth.ply"
        write_ply(truth, phantom.bubbles)
    write_scan(out / "scan.h5", scan)
    shape, extent = truth_grid(phantom)
    meta = {"phantom": phantom_name, "ndim": phantom.ndim, "seed": seed, "size": list(phantom.size),
            "liquid_attenuation": phantom.liquid_attenuation, "bubble_contrast": phantom.contrast,
            "bubbles": len(phantom.bubbles), "grid_shape": list(shape), "grid_extent": list(extent),
            "angles": angles, "photons": photons, "beam": beam, "truth": truth.name}
    atomic_write_text(out / "phantom.json", json.dumps(meta, indent=2))
    finish_outputs(out, [out / "scan.h5", truth, out / "phantom.json"], command="simulate")
    return out / "scan.h5", truth, meta


def simulate_dynamic_to_dir(out, phantom_name="expanding2d", *, subscans=8, projections_per_subscan=50,
                            photons=1e4, seed=0, beam=None, det_count=None, n_bubbles=None,
                            seconds_per_projection=0.01, foam=None):
    """Simulate a dynamic scan of an expanding foam into ``out``.

    Writes ``scan.h5`` (all projections in acquisition order, root attribute
    ``projections_per_subscan``, ``/exchange/time``), ``truth/subscan_NNNN.json|ply``
    (the foam at each subscan's mid-time, bubble ids = phantom bubble
    indices) and ``phantom.json`` (``truth`` names the folder; ``grid_*``
    cover the final, largest container). ``foam``: more options of
    :func:`~bubsub.core.foam.phantoms.foam2d` / ``foam3d`` (size, radius_range, ...).
    """
    from bubsub.core.foam.expanding import expanding2d, expanding3d, simulate_expanding


    if phantom_name not in DYNAMIC_PHANTOMS:
        raise ValueError(f"unknown dynamic phantom {phantom_name!r}; choose one of {DYNAMIC_PHANTOMS}")
    if phantom_name == "flowing3d":
        if beam not in (None, "parallel"):
            raise ValueError("the flowing3d phantom is a parallel-beam scan; drop --beam cone")
        return simulate_flowing_to_dir(out, subscans=subscans, projections_per_subscan=projections_per_subscan,
                                       photons=photons, seed=seed, det_count=det_count, n_bubbles=n_bubbles,
                                       seconds_per_projection=seconds_per_projection, **(foam or {}))
    out = Path(out)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    kw = dict(foam or {}, **({"n_bubbles": n_bubbles} if n_bubbles else {}))
    foam = expanding2d(seed, **kw) if phantom_name == "expanding2d" else expanding3d(seed, **kw)
    beam = beam or ("parallel" if foam.ndim == 2 else "cone")
    geometry = make_geometry(foam.ndim, beam, projections_per_subscan, det_count, repeat=subscans)
    scan, mid = simulate_expanding(foam, geometry, projections_per_subscan=projections_per_subscan,
                                   photons=photons, seed=seed, seconds_per_projection=seconds_per_projection)
    for k, t in enumerate(mid):
        state = foam.at(t)
        if foam.ndim == 2:
            write_polygons_json(out / "truth" / f"subscan_{k:04d}.json", state.bubbles)
        else:
            write_ply(out / "truth" / f"subscan_{k:04d}.ply", state.bubbles)
    write_scan(out / "scan.h5", scan)
    shape, extent = truth_grid(foam.final)
    times = scan.time.reshape(subscans, projections_per_subscan).mean(axis=1)
    meta = {"phantom": phantom_name, "ndim": foam.ndim, "seed": seed, "size": list(foam.final.size),
            "liquid_attenuation": foam.final.liquid_attenuation, "bubble_contrast": foam.final.contrast,
            "bubbles": foam.n_bubbles, "grid_shape": list(shape), "grid_extent": list(extent),
            "subscans": subscans, "projections_per_subscan": projections_per_subscan,
            "angles": subscans * projections_per_subscan, "photons": photons, "beam": beam, "truth": "truth",
            "subscan_times": times.tolist(), "subscan_phase": mid.tolist(),
            "seconds_per_projection": seconds_per_projection}
    atomic_write_text(out / "phantom.json", json.dumps(meta, indent=2))
    truths = [out / "truth" / f"subscan_{k:04d}.{'json' if foam.ndim == 2 else 'ply'}" for k in range(len(mid))]
    finish_outputs(out, [out / "scan.h5", out / "phantom.json", *truths], command="simulate")
    return out / "scan.h5", out / "truth", meta


def simulate_flowing_to_dir(out, *, subscans=None, projections_per_subscan=None, photons=1e4, seed=0,
                            det_count=None, n_bubbles=None, seconds_per_projection=0.01, **foam):
    """Simulate a flowing, coarsening foam column's dynamic scan into ``out`` (:mod:`bubsub.core.foam.flowing`).

    Defaults (:data:`~bubsub.core.foam.flowing.FLOWING_DEFAULTS`): 12 subscans of 40 parallel projections over
    180 degrees each, continuous rotation, 128 x 384 pixels of 12 um, ~150 bubbles in view. ``det_count``
    sets the columns (a third as many rows) and keeps the field of view: the pixel is ``0.012 * 384 / det_count``
    mm. ``foam``: more options of :func:`~bubsub.core.foam.flowing.flowing_foam` (``flow``, ``vanishing``,
    ``coalescences``, ...). Writes what :func:`~bubsub.core.foam.flowing_scan.write_flowing` lists.

    Returns
    -------
    scan : Path
    truth : Path
        The per-subscan truth folder.
    meta : dict
        ``phantom.json``.
    """
    from bubsub.core.foam.flowing import FLOWING_DEFAULTS, flowing_foam
    from bubsub.core.foam.flowing_scan import simulate_flowing, write_flowing


    d = FLOWING_DEFAULTS
    cols = det_count or d["cols"]
    if cols < 3:
        raise ValueError(f"--det-count must be at least 3 for flowing3d (rows are a third of it), got {cols}")
    per = projections_per_subscan or d["projections_per_subscan"]
    flowing = flowing_foam(n_bubbles or d["n_bubbles"], seed=seed, rows=cols // 3, cols=cols,
                           pixel_size=d["pixel_size"] * (d["cols"] / cols), subscans=subscans or d["subscans"], **foam)
    scan = simulate_flowing(flowing, projections_per_subscan=per, photons=photons,
                            seconds_per_projection=seconds_per_projection)
    out = Path(out)
    files, meta = write_flowing(out, flowing, scan, seconds_per_projection=seconds_per_projection)
    finish_outputs(out, files, command="simulate")
    return out / "scan.h5", out / "truth", meta


def simulate_raw_to_dir(out, *, seed=0, n_bubbles=8, foam_size=5.6, **settings):
    """Simulate a raw beamline scan: ``raw.h5`` (Data Exchange counts), ``truth.json`` and ``phantom.json``.

    The foam (``n_bubbles`` in a ``foam_size`` mm square) sits in the
    cylindrical container of :mod:`bubsub.core.foam.raw`; ``settings`` go to
    :func:`bubsub.core.foam.raw.raw_settings`.
    """
    from bubsub.core.foam.raw import raw_settings, simulate_raw, write_raw

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    s = raw_settings(seed=seed, **settings)
    phantom = phantoms.foam2d(seed, n_bubbles=n_bubbles, size=foam_size, liquid_attenuation=s.liquid_mu)
    raw = simulate_raw(phantom, s)
    write_raw(out / "raw.h5", raw, s)
    truth = out / "truth.json"
    write_polygons_json(truth, phantom.bubbles)
    shape, extent = truth_grid(phantom)
    meta = {"phantom": "foam2d-raw", "ndim": 2, "seed": seed, "size": list(phantom.size),
            "liquid_attenuation": phantom.liquid_attenuation, "bubble_contrast": phantom.contrast,
            "bubbles": len(phantom.bubbles), "grid_shape": list(shape), "grid_extent": list(extent),
            "angles": s.n_angles, "photons": s.photons, "beam": "parallel", "truth": truth.name,
            "raw": dataclasses.asdict(s), "axis_column": s.axis_column, "delta_beta": s.delta_beta}
    atomic_write_text(out / "phantom.json", json.dumps(meta, indent=2))
    return out / "raw.h5", truth, meta
