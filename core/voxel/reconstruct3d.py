"""Iterative voxel reconstructions of 3D scans (and 2D scans by embedding): the solver driver."""

from __future__ import annotations

import numpy as np

from bubsub.core.voxel import solvers
from bubsub.core.voxel.fdk import fdk
from bubsub.core.voxel.grid import voxel_sizes
from bubsub.core.voxel.projector3d import VoxelProjector

__all__ = ["reconstruct_3d", "iterate", "check_upper", "METHODS_3D"]

#: Methods of :func:`reconstruct_3d` and their default iteration counts.
METHODS_3D = {"fdk": None, "fbp": None, "sirt": 50, "cgls": 15, "lsqr": 15, "tv": 50, "bb": 30}

_F32 = np.float32


# -- driver -------------------------------------------------------------------------
def reconstruct_3d(
    method,
    projections,
    geometry,
    shape,
    extent=None,
    *,
    pixel_size=None,
    centre=None,
    iterations=None,
    tv_weight=None,
    nonneg=False,
    filter="ram-lak",
    isotropic=True,
    detector_binning="auto",
    threads=None,
    x0=None,
    upper=None,
    callback=None,
):
    """Voxel reconstruction of a 3D scan (numpy projector; also accepts 2D scans).

    Cost: FDK is one backprojection; every SIRT/CGLS/TV iteration is one
    forward and one backprojection (about 3 s together for 200 x 200 x 100
    voxels and 25 projections of 256 x 512 on two busy cores).

    Parameters
    ----------
    method : {'fdk', 'fbp', 'sirt', 'cgls', 'lsqr', 'tv', 'bb'}
        ``fdk``/``fbp``: :func:`fdk`; ``sirt``, ``cgls``, ``lsqr``: the
        solvers of :mod:`bubsub.core.voxel.solvers` on :class:`VoxelProjector`;
        ``tv``: :func:`bubsub.core.voxel.solvers.tv_pdhg`.
    projections : ndarray float, ``(angle, row, col)`` (or ``(angle, col)``)
    geometry : ScanGeometry or ASTRA proj_geom dict
    shape : (slices, rows, cols) (or (rows, cols) for 2D)
    extent, pixel_size, centre
        The grid.
    iterations : int, optional
        Defaults from :data:`METHODS_3D`.
    tv_weight : float
        Required for ``tv`` (see :func:`bubsub.core.voxel.solvers.tv_pdhg`).
    nonneg : bool
        Non-negativity constraint for ``sirt`` and ``tv`` (ignored by ``cgls``/``lsqr``).
    filter : str
        FDK filter.
    isotropic : bool
        Isotropic (True) or anisotropic l1 TV.
    detector_binning, threads
        See :class:`VoxelProjector`.
    x0 : ndarray, optional
        Initial volume for the iterative methods.
    upper : float, optional
        Upper bound on every voxel (``bb`` only: projected onto before each gradient).
    callback : callable(k, x), optional

    Returns
    -------
    ndarray float32, shape ``shape``
    """
    if method not in METHODS_3D:
        raise ValueError(f"unknown method {method!r}; expected one of {sorted(METHODS_3D)}")
    check_upper(method, upper)
    if method in ("fdk", "fbp"):
        return fdk(projections, geometry, shape, extent, pixel_size=pixel_size, centre=centre,
                   filter=filter, threads=threads)
    op = VoxelProjector(geometry, shape, extent, pixel_size=pixel_size, centre=centre,
                        detector_binning=detector_binning, threads=threads)
    return iterate(method, op, projections, iterations, tv_weight, nonneg, isotropic, x0, callback,
                    METHODS_3D, upper=upper)


def check_upper(method, upper):
    """Refuse an upper bound given to a method that does not take one (only ``bb`` does)."""
    if upper is not None and method != "bb":
        raise ValueError(f"an upper bound is only taken by method 'bb', not {method!r}")


def iterate(method, op, projections, iterations, tv_weight, nonneg, isotropic, x0, callback, defaults, *,
            upper=None):
    """Run an iterative method on an operator (shared by the 2D and 3D drivers)."""
    it = defaults[method] if iterations is None else iterations
    b = np.asarray(projections, dtype=_F32)
    if method == "sirt":
        return solvers.sirt(op, b, it, x0=x0, nonneg=nonneg, callback=callback)
    if method == "cgls":
        return solvers.cgls(op, b, it, x0=x0, callback=callback)
    if method == "bb":
        return solvers.pgd_bb(op, b, it, x0=x0, nonneg=nonneg, upper=upper, callback=callback)
    if method == "lsqr":
        if x0 is not None:
            raise ValueError("lsqr does not take x0")
        return solvers.lsqr(op, b, it)
    if method == "tv":
        if tv_weight is None:
            raise ValueError("method 'tv' needs tv_weight")
        h = voxel_sizes(op.shape, op.extent)
        return solvers.tv_pdhg(op, b, tv_weight, it, voxel_sizes=h, isotropic=isotropic,
                               nonneg=nonneg, x0=x0, callback=callback)
    raise ValueError(f"method {method!r} is not iterative")
