"""Simulated scans on disk: a phantom, its scan geometry, ``scan.h5`` and the ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["PHANTOMS", "make_phantom", "make_geometry", "truth_grid", "simulate_to_dir"]

PHANTOMS = ("foam2d", "foam3d", "foam3d-benchmark")


def make_phantom(name, seed, n_bubbles=None):
    from bubsub.core.foam import phantoms

    if name == "foam2d":
        return phantoms.foam2d(seed, **({"n_bubbles": n_bubbles} if n_bubbles else {}))
    if name == "foam3d":
        return phantoms.foam3d(seed, **({"n_bubbles": n_bubbles} if n_bubbles else {}))
    if name == "foam3d-benchmark":
        return phantoms.foam3d_benchmark()
    raise ValueError(f"unknown phantom {name!r}; choose one of {PHANTOMS}")


def make_geometry(ndim, beam, n_angles, det_count=None, rows=None):
    """The scans of the paper: 2D parallel over [0, pi), 3D cone over [0, 2 pi)."""
    from bubsub.core import ScanGeometry
    from bubsub.core.foam.simulate import default_geometry_2d

    if ndim == 2:
        # a 14.4 mm detector sees the whole 10 mm square at every angle
        cols = det_count or 2400
        if beam == "parallel":
            return default_geometry_2d(n_angles, det_count=cols, pixel_size=14.4 / cols)
        angles = np.linspace(0, 2 * np.pi, n_angles, endpoint=False)
        return ScanGeometry.cone(angles, source_origin=300.0, origin_detector=15.0, pixel_size=15.2 / cols, cols=cols)
    cols = det_count or 512
    rows = rows or cols // 2
    pixel = 0.06 * 512 / cols
    if beam == "parallel":
        angles = np.linspace(0, np.pi, n_angles, endpoint=False)
        return ScanGeometry.parallel(angles, pixel_size=pixel, cols=cols, rows=rows)
    angles = np.linspace(0, 2 * np.pi, n_angles, endpoint=False)
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
    """Simulate a scan and write ``scan.h5``, ``truth.json|ply`` and ``phantom.json`` to ``out``."""
    from bubsub.core.io.atomic import atomic_write_text
    from bubsub.core.io.meshio import write_ply, write_polygons_json
    from bubsub.core.io.scanfile import write_scan
    from bubsub.core.foam.simulate import simulate_2d, simulate_3d

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
    return out / "scan.h5", truth, meta
