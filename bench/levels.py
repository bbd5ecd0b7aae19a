"""Benchmark "levels": the fit's data levels against a long fit on the full detector, from the same start.

``python -m bubsub.bench levels SCAN [--reference 300] [--iterations 80] [--coarse 1 3] [--cache FILE]``

The start is the pipeline's, with its default settings: the voxel preview,
the initial spheres (distance-transform centres; the field-of-view model's
edge seeds) and the radius-only fit on the coarsest level's pixels, made
once (``--cache`` keeps them for a second run). Then, each from
that start in the same process:

* the reference: ``--reference`` iterations on the full detector, no
  convergence test;
* for each ``--coarse`` factor c: the default data levels
  (:func:`bubsub.clients.optimise.levels.bin_factors`), the binned levels capped
  at c x ``--iterations`` and the full detector at ``--iterations``, with the
  pipeline's convergence test.

Printed per run: the final objective on the full detector and its excess
over the reference's, each level's iterations and stop reason, the cost in
full-detector evaluations (a level binned by f counts 1/f^2 per
evaluation), and CPU seconds. To make a column scan:
``bubsub simulate --phantom column --bubbles 150 --det-count 384 --out DIR``.
"""

from __future__ import annotations

import argparse
import pickle
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from bubsub.clients.optimise import levels
from bubsub.clients.optimise.levels import bin_factors
from bubsub.clients.pipeline.static.initial import default_detector
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, coarse_radii, settings_initial, settings_preview
from bubsub.clients.pipeline.static.resolution import levels_by_size
from bubsub.core import MeshProjector
from bubsub.core.io.scanfile import read_scan

__all__ = ["main", "start", "run"]


def start(scan):
    """The pipeline's initial bubbles of ``scan`` (:class:`bubsub.core.io.scanfile.Scan`), radius-fitted, with
    the default settings (:mod:`bubsub.clients.pipeline.reconstruct`'s own steps)."""
    s = ReconstructionSettings(progress=False)
    g, d, c = scan.geometry, scan.bubble_data, scan.bubble_contrast
    image, extent = settings_preview(d, g, c, s)
    surfaces, _ = settings_initial(image, extent, c, MeshProjector(g), d, s)
    if s.estimate_radii and default_detector(s.detector, g.ndim) != "auto":  # "auto" fitted the radii already
        surfaces = coarse_radii(surfaces, g, d, bin_factors(g)[0], s)
    return levels_by_size(surfaces, g, s.levels, s.facet_pixels)


def run(scan, surfaces, *, factors, iterations, coarse, rtol):
    """One fit from ``surfaces``; returns its row of the table (a dict)."""
    projector = MeshProjector(scan.geometry)
    old = levels.COARSE_ITERATIONS
    levels.COARSE_ITERATIONS = coarse
    try:
        t, cpu = time.perf_counter(), time.process_time()
        result, report = levels.fit_levels(projector, surfaces, scan.bubble_data, factors=factors,
                                           iterations=iterations, rtol=rtol)
        wall, cpu = time.perf_counter() - t, time.process_time() - cpu
    finally:
        levels.COARSE_ITERATIONS = old
    return {"objective": float(projector.objective(result.surfaces, scan.bubble_data)[0]), "wall": wall, "cpu": cpu,
            "cost": sum(r["evaluations"] / r["bin"] ** 2 for r in report),
            "levels": " + ".join(f"{r['iterations']} at bin {r['bin']} ({r['stop_reason']})" for r in report)}


def main(argv=None):

    p = argparse.ArgumentParser(prog="python -m bubsub.bench levels", description=__doc__.split("\n\n")[0])
    p.add_argument("scan", help="a scan file (e.g. bubsub simulate --phantom column)")
    p.add_argument("--reference", type=int, default=300, help="iterations of the reference fit (default 300)")
    p.add_argument("--iterations", type=int, default=80, help="the full detector's cap (default 80)")
    p.add_argument("--coarse", type=int, nargs="+", default=[1, 3],
                   help="binned levels' caps, in units of --iterations (default 1 3)")
    p.add_argument("--rtol", type=float, default=2e-4, help="the levels' convergence test (default 2e-4)")
    p.add_argument("--cache", help="pickle of the initial bubbles (written when missing)")
    a = p.parse_args(argv)
    threadpool_limits(1, "blas")
    scan = read_scan(a.scan)
    cache = Path(a.cache) if a.cache else None
    if cache is not None and cache.exists():
        surfaces = pickle.loads(cache.read_bytes())
    else:
        surfaces = start(scan)
        if cache is not None:
            cache.write_bytes(pickle.dumps(surfaces))
    n = sum(s.vertices.size for s in surfaces)
    print(f"{a.scan}: {len(surfaces)} bubbles, {n} unknowns, detector {scan.geometry.shape}", flush=True)
    rows = [("reference", run(scan, surfaces, factors=[1], iterations=a.reference, coarse=1, rtol=None))]
    for c in a.coarse:
        rows.append((f"levels {bin_factors(scan.geometry)}, binned cap {c} x {a.iterations}",
                     run(scan, surfaces, factors=bin_factors(scan.geometry), iterations=a.iterations, coarse=c,
                         rtol=a.rtol)))
    ref = rows[0][1]["objective"]
    print("| fit | objective | above reference | full-detector evaluations | CPU s | iterations |")
    print("|---|---|---|---|---|---|")
    for name, r in rows:
        print(f"| {name} | {r['objective']:.5g} | {100 * (r['objective'] / ref - 1):+.2f} % | {r['cost']:.0f} | "
              f"{r['cpu']:.0f} | {r['levels']} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
