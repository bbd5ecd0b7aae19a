"""Iterative voxel reconstruction on any linear projector: SIRT, CGLS, LSQR, TV (PDHG), BB.

The solvers take an *operator*: any object with

* ``shape`` -- the image / volume shape,
* ``proj_shape`` -- the projection array shape,
* ``forward(x) -> y`` (``A x``) and ``adjoint(y) -> x`` (``A^T y``), float32 arrays.

:class:`bubsub.core.voxel.astra2d.AstraProjector2D` (ASTRA CPU, 2D) and
:class:`bubsub.core.voxel.projector3d.VoxelProjector` (numpy, 2D and 3D) are such
operators; both have exact adjoints, which CGLS and LSQR rely on.
"""

from __future__ import annotations

import numbers

import numpy as np

from bubsub.core.validate import check_int

__all__ = ["sirt", "cgls", "lsqr", "tv_pdhg", "pgd_bb", "check_iterations"]


def _check(op, b, x0):
    b = np.asarray(b, dtype=np.float32)
    if b.shape != tuple(op.proj_shape):
        raise ValueError(f"projection data must have shape {tuple(op.proj_shape)}, got {b.shape}")
    if not np.all(np.isfinite(b)):
        raise ValueError("projection data contain NaN or inf")
    if x0 is None:
        x = np.zeros(op.shape, dtype=np.float32)
    else:
        x = np.array(x0, dtype=np.float32, copy=True)
        if x.shape != tuple(op.shape):
            raise ValueError(f"x0 must have shape {tuple(op.shape)}, got {x.shape}")
    return b, x


def check_iterations(n, name="iterations"):
    """``n`` as an int, or a ValueError naming ``name`` unless it is a non-negative integer."""
    return check_int(n, name, 0)


def _dot(a, b):
    return float(np.dot(a.ravel().astype(np.float64), b.ravel().astype(np.float64)))


def _safe_inverse(s, rel=1e-6):
    """1/s where s is clearly positive, 0 elsewhere (rays or voxels nothing touches)."""
    s = np.asarray(s, dtype=np.float32)
    tol = rel * float(s.max()) if s.size and s.max() > 0 else 0.0
    out = np.zeros_like(s)
    ok = s > tol
    out[ok] = 1.0 / s[ok]
    return out


def sirt(op, b, iterations=100, *, x0=None, nonneg=False, callback=None):
    """Simultaneous Iterative Reconstruction Technique.

    ``x <- x + C A^T R (b - A x)`` with ``R = 1 / (A 1)``, ``C = 1 / (A^T 1)``.

    Parameters
    ----------
    op : operator (see module docstring)
    b : ndarray, shape ``op.proj_shape``
        Projection data.
    iterations : int
    x0 : ndarray, shape ``op.shape``, optional
        Initial image (zeros by default).
    nonneg : bool
        Clip negative values after every iteration.
    callback : callable(k, x), optional
        Called after every iteration with the iteration number and the image.

    Returns
    -------
    ndarray float32, shape ``op.shape``
    """
    n = check_iterations(iterations)
    b, x = _check(op, b, x0)
    R = _safe_inverse(op.forward(np.ones(op.shape, dtype=np.float32)))
    C = _safe_inverse(op.adjoint(np.ones(op.proj_shape, dtype=np.float32)))
    for k in range(n):
        x += C * op.adjoint(R * (b - op.forward(x)))
        if nonneg:
            np.maximum(x, 0.0, out=x)
        if callback is not None:
            callback(k, x)
    return x


def cgls(op, b, iterations=20, *, x0=None, callback=None):
    """Conjugate gradients on the normal equations, ``min ||A x - b||^2``.

    Equivalent to LSQR in exact arithmetic (the paper's "LSQR" baseline);
    stops early if the normal-equation residual vanishes.

    Parameters
    ----------
    op : operator with an exact adjoint
    b : ndarray, shape ``op.proj_shape``
    iterations : int
    x0 : ndarray, shape ``op.shape``, optional
    callback : callable(k, x), optional

    Returns
    -------
    ndarray float32, shape ``op.shape``
    """
    n = check_iterations(iterations)
    b, x = _check(op, b, x0)
    r = b - op.forward(x) if x0 is not None else b.copy()
    s = op.adjoint(r)
    p = s.copy()
    gamma = _dot(s, s)
    gamma0 = gamma
    for k in range(n):
        if gamma <= 1e-30 * max(gamma0, 1e-300):
            break
        q = op.forward(p)
        qq = _dot(q, q)
        if qq <= 0:
            break
        alpha = gamma / qq
        x += np.float32(alpha) * p
        r -= np.float32(alpha) * q
        s = op.adjoint(r)
        gamma_new = _dot(s, s)
        p *= np.float32(gamma_new / gamma)
        p += s
        gamma = gamma_new
        if callback is not None:
            callback(k, x)
    return x


def pgd_bb(op, b, iterations=30, *, x0=None, nonneg=True, upper=None, callback=None):
    """Projected gradient descent with Barzilai-Borwein steps on ``0.5 ||A x - b||^2``.

    The paper's 4D voxel baseline (30 iterations, ``x >= 0``). The first step
    is the exact line-search step along the gradient, ``|g|^2 / |A g|^2``;
    later steps are BB1, ``s.s / s.y`` with ``s`` the last change of ``x``
    and ``y`` that of the gradient (kept when ``s.y <= 0``). Every iterate is
    projected onto the box before its gradient is taken: a bound applied
    afterwards (by a callback) would leave the BB steps measuring the gradient
    of a point the iteration never keeps, which can stall the descent.

    Parameters
    ----------
    op : operator (see module docstring)
    b : ndarray, shape ``op.proj_shape``
    iterations : int
    x0 : ndarray, shape ``op.shape``, optional
    nonneg : bool
        Project onto ``x >= 0`` after every step.
    upper : float, optional
        Also project onto ``x <= upper`` after every step.
    callback : callable(k, x), optional

    Returns
    -------
    ndarray float32, shape ``op.shape``
    """
    n = check_iterations(iterations)
    b, x = _check(op, b, x0)
    if upper is not None and not (np.isfinite(upper) and upper > (0.0 if nonneg else -np.inf)):
        raise ValueError(f"upper must be a finite bound above the lower one, got {upper!r}")

    def project(v):
        if nonneg:
            np.maximum(v, 0.0, out=v)
        if upper is not None:
            np.minimum(v, np.float32(upper), out=v)

    project(x)
    g = op.adjoint(op.forward(x) - b)
    gg = _dot(g, g)
    ag = op.forward(g)
    step = gg / _dot(ag, ag) if gg > 0 and _dot(ag, ag) > 0 else 0.0
    for k in range(n):
        if step <= 0:
            break
        x_new = x - np.float32(step) * g
        project(x_new)
        g_new = op.adjoint(op.forward(x_new) - b)
        s_, y_ = x_new - x, g_new - g
        sy = _dot(s_, y_)
        if sy > 0:
            step = _dot(s_, s_) / sy
        x, g = x_new, g_new
        if callback is not None:
            callback(k, x)
    return x


def lsqr(op, b, iterations=20, *, damp=0.0):
    """LSQR (scipy) on the operator, ``min ||A x - b||^2 + damp^2 ||x||^2``.

    Parameters
    ----------
    op : operator with an exact adjoint
    b : ndarray, shape ``op.proj_shape``
    iterations : int
        Iteration limit.
    damp : float
        Tikhonov damping.

    Returns
    -------
    ndarray float32, shape ``op.shape``
    """
    from scipy.sparse.linalg import LinearOperator, lsqr as _lsqr  # heavy: not at `import bubsub.core`

    n = check_iterations(iterations)
    b, _ = _check(op, b, None)
    nx, ny = int(np.prod(op.shape)), int(np.prod(op.proj_shape))
    A = LinearOperator(
        (ny, nx),
        matvec=lambda v: op.forward(np.asarray(v, np.float32).reshape(op.shape)).ravel().astype(np.float64),
        rmatvec=lambda v: op.adjoint(np.asarray(v, np.float32).reshape(op.proj_shape)).ravel().astype(np.float64),
        dtype=np.float64,
    )
    if n == 0:
        return np.zeros(op.shape, dtype=np.float32)
    sol = _lsqr(A, b.ravel().astype(np.float64), damp=float(damp), iter_lim=n, atol=0, btol=0, conlim=0)[0]
    return sol.reshape(op.shape).astype(np.float32)


# -- total variation ---------------------------------------------------------------
def _grad(x, s):
    """Weighted forward differences, shape ``(ndim, *x.shape)``; zero across the far edge."""
    g = np.zeros((x.ndim,) + x.shape, dtype=np.float32)
    for a in range(x.ndim):
        sl_lo = [slice(None)] * x.ndim
        sl_hi = [slice(None)] * x.ndim
        sl_lo[a] = slice(0, -1)
        sl_hi[a] = slice(1, None)
        np.subtract(x[tuple(sl_hi)], x[tuple(sl_lo)], out=g[a][tuple(sl_lo)])
        g[a] *= np.float32(s[a])
    return g


def _grad_adjoint(y, s):
    """Adjoint of :func:`_grad` (minus the divergence)."""
    ndim = y.shape[0]
    out = np.zeros(y.shape[1:], dtype=np.float32)
    for a in range(ndim):
        ya = y[a] * np.float32(s[a])
        sl_lo = [slice(None)] * ndim
        sl_hi = [slice(None)] * ndim
        sl_lo[a] = slice(0, -1)
        sl_hi[a] = slice(1, None)
        out[tuple(sl_lo)] -= ya[tuple(sl_lo)]
        out[tuple(sl_hi)] += ya[tuple(sl_lo)]
    return out


def tv_pdhg(
    op,
    b,
    tv_weight,
    iterations=200,
    *,
    voxel_sizes=None,
    isotropic=True,
    nonneg=True,
    x0=None,
    callback=None,
):
    """Total-variation regularised least squares by preconditioned PDHG (Chambolle-Pock).

    Minimises::

        1/2 ||A x - b||^2 + tv_weight * TV(x)   [+ indicator(x >= 0)]

    with ``TV(x) = sum_voxels V |(dx_1/h_1, ..., dx_d/h_d)|`` (``V`` the voxel
    volume, ``h_a`` the voxel sizes, ``dx_a`` forward differences), a
    discretisation of ``int |grad f|`` so that ``tv_weight`` does not depend on
    the grid resolution. ``isotropic=False`` uses the l1 norm of the gradient
    (anisotropic TV). The step sizes are the diagonal preconditioners of Pock
    and Chambolle (2011), so no operator norm is needed.

    Parameters
    ----------
    op : operator with an exact adjoint
    b : ndarray, shape ``op.proj_shape``
    tv_weight : float
        Regularisation weight (>= 0).
    iterations : int
    voxel_sizes : (ndim,) float, optional
        Voxel sizes in array-axis order (mm); unit voxels by default.
    isotropic : bool
    nonneg : bool
        Constrain ``x >= 0``.
    x0 : ndarray, shape ``op.shape``, optional
    callback : callable(k, x), optional

    Returns
    -------
    ndarray float32, shape ``op.shape``
    """
    n = check_iterations(iterations)
    bad = isinstance(tv_weight, bool) or not isinstance(tv_weight, numbers.Real)
    if bad or not np.isfinite(tv_weight) or tv_weight < 0:
        raise ValueError(f"tv_weight must be a non-negative number, got {tv_weight!r}")
    b, x = _check(op, b, x0)
    ndim = len(op.shape)
    h = np.ones(ndim) if voxel_sizes is None else np.asarray(voxel_sizes, dtype=float)
    if h.shape != (ndim,) or not np.all(np.isfinite(h)) or np.any(h <= 0):
        raise ValueError(f"voxel_sizes must be {ndim} positive numbers, got {voxel_sizes!r}")
    s = np.prod(h) / h  # weight of the differences along each axis
    lam = np.float32(tv_weight)

    sigma1 = _safe_inverse(op.forward(np.ones(op.shape, dtype=np.float32)))
    colsum = op.adjoint(np.ones(op.proj_shape, dtype=np.float32)) + np.float32(2.0 * s.sum())
    tau = _safe_inverse(colsum)
    sigma2 = np.float32(1.0 / (2.0 * s.max()))

    y1 = np.zeros(op.proj_shape, dtype=np.float32)
    y2 = np.zeros((ndim,) + tuple(op.shape), dtype=np.float32)
    xbar = x.copy()
    for k in range(n):
        y1 += sigma1 * (op.forward(xbar) - b)
        y1 /= 1.0 + sigma1
        y2 += sigma2 * _grad(xbar, s)
        if isotropic:
            norm = np.sqrt(np.sum(y2 * y2, axis=0))
            if lam > 0:
                np.maximum(norm / lam, 1.0, out=norm)
                y2 /= norm
            else:
                y2[...] = 0.0
        else:
            np.clip(y2, -lam, lam, out=y2)
        x_new = x - tau * (op.adjoint(y1) + _grad_adjoint(y2, s))
        if nonneg:
            np.maximum(x_new, 0.0, out=x_new)
        np.subtract(2.0 * x_new, x, out=xbar)
        x = x_new
        if callback is not None:
            callback(k, x)
    return x
