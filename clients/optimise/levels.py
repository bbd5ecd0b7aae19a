"""Coarse to fine in the data: the fit on binned projections first, the full detector last.

On a large scan most of the fit's iterations move bubbles by more than a
pixel: they need not see every pixel. :func:`fit_levels` fits the detector
binned by ``2^(k-1)``, ..., 2, then 1 (:meth:`ScanGeometry.binned`, the mean
of each block of pixels: a binned pixel holds the mean line integral of the
pixels it joins), each level warm-started from the one before and ended on
convergence (:func:`bubsub.clients.optimise.fit.fit`'s ``rtol``, times
``f^2`` on a level binned by ``f``: :func:`level_rtol`) or its iteration
cap. A binned level's surfaces are subdivided one Loop step fewer per
halving of the detector (:func:`coarse_surfaces`). A binned
level costs about a quarter of the next one's evaluations, so it may take
:data:`COARSE_ITERATIONS` times as many iterations for 3/4 of the next
level's cost. On a large column both levels end on convergence within a
percent of a fit several times as long on the full detector, for a
fraction of its full-detector evaluations (``python -m bubsub.bench levels``
measures it; docs/large-scans.md).
"""

from __future__ import annotations

import time

import numpy as np

from bubsub.core import MeshProjector, ScanGeometry
from bubsub.core.malloc import release_free_memory

from bubsub.clients.optimise.fit import STALL_ITERATIONS, fit

__all__ = ["bin_factors", "coarse_surfaces", "fit_levels", "level_rtol", "MIN_BINNED_PIXELS", "COARSE_ITERATIONS"]

#: A binned level's iteration cap, in units of the full detector's.
COARSE_ITERATIONS = 3

#: Least detector rows and columns (3D; columns in 2D) of a binned level: coarser ones see too little.
MIN_BINNED_PIXELS = 48


def bin_factors(geometry, levels=None):
    """The binning factor of each level, coarsest first, ending with 1.

    Parameters
    ----------
    geometry : ScanGeometry
    levels : int, optional
        Number of levels; default as many as keep the coarsest detector at least
        :data:`MIN_BINNED_PIXELS` pixels along each axis, at most 2 (3D only; 2D scans are small).

    Returns
    -------
    list of int
    """
    if levels is not None:
        if isinstance(levels, bool) or not isinstance(levels, int) or levels < 1:
            raise ValueError(f"data levels must be a positive integer, got {levels!r}")
        return [2 ** k for k in range(levels - 1, -1, -1)]
    if geometry.ndim != 3:
        return [1]
    smallest = min(geometry.det_rows, geometry.det_cols)
    n = 1
    while n < 2 and smallest // 2 ** n >= MIN_BINNED_PIXELS:
        n += 1
    return [2 ** k for k in range(n - 1, -1, -1)]


def level_rtol(rtol, factor):
    """The convergence test of a level binned by ``factor``: ``rtol x factor^2`` (None stays None).

    The test compares the objective's fall over a few iterations with the objective itself. Binning by ``f``
    leaves ``1/f^2`` as many values, each the mean of ``f^2`` pixels: the objective's fall for the same moves
    of the bubbles is about ``1/f^2`` of the full detector's, but its noise floor, which dominates the objective
    near convergence, ``1/f^4`` (``f^2`` fewer values, each with ``f^2`` less variance). So the same
    progress is up to ``f^2`` times larger relative to a binned objective, and the same relative test held
    a binned level to up to ``f^2`` times less progress than the full detector, and a 2 x 2 level would
    run to its iteration cap (``python -m bubsub.bench levels`` measures both; docs/large-scans.md).
    """
    return None if rtol is None else float(rtol) * factor ** 2


def coarse_surfaces(surfaces, factor, levels):
    """``surfaces`` with their control meshes subdivided ``log2(factor)`` fewer times than ``levels`` (one per
    surface), and at least once (unless ``levels`` asks for fewer).

    Binning the detector by 2 doubles the pixel and one Loop step fewer doubles the fine edges, so a
    binned level's projected faces cover as many pixels as the full detector's: on the binned detector
    most faces of the full subdivision hit one lattice point or none and the projection's cost is
    theirs (docs/large-scans.md). The control vertices, the unknowns, are the same at every level.
    One level fewer makes a sphere 1.7 % larger; the control vertices are not scaled to keep each bubble's
    size (``SubdivisionSurface.with_levels(keep_size=True)``): the full-detector level then starts farther
    from its optimum and runs longer for an objective hardly lower.
    """
    drop = int(round(np.log2(factor)))
    return [s.with_levels(max(min(n, 1), n - drop)) for s, n in zip(surfaces, levels)]


def fit_levels(projector, surfaces, data, *, factors, iterations, rtol=None, penalty=None, progress=False,
               factory=None, rtol_window=STALL_ITERATIONS):
    """Fit ``surfaces`` level by level (see the module docstring).

    Parameters
    ----------
    projector : MeshProjector or RemoteJob
        The full detector's (the last level's); a remote job holds its data.
    surfaces : list of SubdivisionSurface
    data : ndarray
        The full detector's projections (binned here for the coarse levels).
    factors : list of int
        :func:`bin_factors`.
    iterations : int
        The full detector's iteration cap; a binned level's is :data:`COARSE_ITERATIONS` times this.
    rtol, rtol_window : float, int
        The full detector's convergence test (:func:`bubsub.clients.optimise.fit.fit`); a binned level's
        is :func:`level_rtol`.
    factory : callable(geometry, data, surfaces) -> projector, optional
        Makes a binned level's projector holding its data (a remote job; ``projector`` is then the
        full detector's job, which holds its own); default a local MeshProjector.

    Returns
    -------
    result : FitResult
        The last level's, with ``iterations``, ``evaluations`` and ``seconds`` summed over the levels.
    levels : list of dict
        Per level: ``bin``, ``detector`` (rows, cols), ``subdivision`` (Loop levels of the fitted
        surfaces: :func:`coarse_surfaces`), ``iterations``, ``evaluations``, ``seconds``,
        ``stop_reason``, ``objective``.
    """
    geometry = projector.geometry if hasattr(projector, "geometry") else None
    final_levels = [s.levels for s in surfaces]
    summary, result = [], None
    total_it = total_ev = 0
    for f in factors:
        t0 = time.perf_counter()
        surfaces = coarse_surfaces(surfaces, f, final_levels)
        if f == 1:  # a remote job (made by ``factory``) holds its own data
            level_projector, level_data = projector, (None if factory is not None else data)
        else:
            if data is None:
                raise ValueError("binned levels need the full detector's data")
            g = geometry.binned(f)
            level_data = ScanGeometry.bin_projections(data, f)
            if factory is not None:
                level_projector, level_data = factory(g, level_data, surfaces), None
            else:
                level_projector = MeshProjector(g, supersampling=getattr(projector, "supersampling", 1),
                                                threads=getattr(projector, "threads", None))
        label = "BubSub fit" if len(factors) == 1 else f"BubSub fit (pixels binned {f} x {f})" if f > 1 \
            else "BubSub fit (full detector)"
        cap = iterations if f == 1 else COARSE_ITERATIONS * iterations
        result = fit(level_projector, surfaces, level_data, iterations=cap, progress=progress,
                     penalty=penalty, rtol=level_rtol(rtol, f), rtol_window=rtol_window, label=label,
                     catch_interrupt=True)
        surfaces = result.surfaces
        total_it += result.iterations
        total_ev += result.evaluations
        shape = level_projector.geometry.shape[1:] if hasattr(level_projector, "geometry") else None
        summary.append({"bin": f, "detector": list(shape) if shape else None,
                        "subdivision": max((s.levels for s in surfaces), default=None), "iterations": result.iterations,
                        "evaluations": result.evaluations, "seconds": time.perf_counter() - t0,
                        "stop_reason": result.stop_reason, "objective": result.objective})
        release_free_memory()  # the level's projector and binned data are gone
        if result.interrupted:
            break
    result.iterations, result.evaluations = total_it, total_ev
    result.seconds = float(sum(level["seconds"] for level in summary))
    result.surfaces = coarse_surfaces(result.surfaces, 1, final_levels)  # an interrupted binned level's too
    return result, summary
