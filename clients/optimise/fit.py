"""The BubSub optimiser: BFGS on the control vertices of all bubbles.

It needs only ``projector.objective(surfaces, data)``, so it runs the same
against a local :class:`bubsub.core.MeshProjector` and a remote job
(:class:`bubsub.clients.RemoteJob`), whose data lives on the server.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg.blas import dger
from scipy.optimize import line_search, minimize

from bubsub.core import SubdivisionSurface

from bubsub.clients.progress import phase

__all__ = ["fit", "estimate_radii", "FitResult"]

#: above this many unknowns, dense BFGS (n x n inverse Hessian) gives way to L-BFGS
DENSE_BFGS_LIMIT = 6000


@dataclass
class FitResult:
    """Outcome of :func:`fit`.

    Attributes
    ----------
    surfaces : list of SubdivisionSurface
        The fitted bubbles (the best iterate seen).
    objective : float
        ``0.5 ||Proj(S x) - d||^2`` at ``surfaces``.
    iterations : int
        Optimiser iterations done.
    evaluations : int
        Objective evaluations (projections) done.
    seconds : float
    history : list of dict
        Per iteration: ``iteration``, ``objective``, ``seconds``.
    interrupted : bool
        True when stopped by Ctrl-C; ``surfaces`` is then the last good iterate.
    method : str
    penalty : float
        The ``penalty`` term included in ``objective`` (0 without one).
    stop_reason : str
        Why the fit stopped: ``"converged"`` (gradient below tolerance, or no
        step decreased the objective any more), ``"iteration limit"``,
        ``"evaluation limit"``, ``"interrupted"`` (Ctrl-C) or ``"stopped by
        callback"``.
    """

    surfaces: list
    objective: float
    iterations: int
    evaluations: int
    seconds: float
    history: list = field(default_factory=list)
    interrupted: bool = False
    method: str = "bfgs"
    stop_reason: str = "iteration limit"
    penalty: float = 0.0


class _Cached:
    """``f`` and ``g`` of one evaluation of ``fun(x) -> (f, g)``, for line searches that ask separately."""

    def __init__(self, fun):
        self.fun = fun
        self.key = None

    def __call__(self, x):
        key = x.tobytes()
        if key != self.key:
            self.value = self.fun(x)
            self.key = key
        return self.value

    def f(self, x):
        return self(x)[0]

    def g(self, x):
        return self(x)[1]


def bfgs(fun, x0, maxiter, callback=None, gtol=1e-10):
    """Dense BFGS with Wolfe line searches and O(n^2) inverse-Hessian updates.

    (scipy's BFGS forms the update with n x n matrix products, O(n^3) per
    iteration, which dominates once a fit has a few hundred bubbles.)

    Parameters
    ----------
    fun : callable(x) -> (f, g)
    x0 : (n,) float
    maxiter : int
    callback : callable(x), optional
        After each iteration.

    Returns
    -------
    x : (n,) float
        Last accepted iterate.
    reason : str
        ``"converged"`` (gradient below ``gtol``, or no step along the
        steepest descent decreases ``f``) or ``"iteration limit"``.
    """
    cached = _Cached(fun)

    def search(p, f, g, old_old_f):
        with warnings.catch_warnings():
            # a failed search is handled below (restart, then stop), not worth a warning
            warnings.filterwarnings("ignore", message="The line search algorithm did not converge")
            return line_search(cached.f, cached.g, x, p, g, f, old_old_f, maxiter=20)

    x = np.array(x0, dtype=float)
    f, g = cached(x)
    H = None  # inverse Hessian, Fortran order for in-place BLAS rank-1 updates
    old_old_f = f + np.linalg.norm(g) / 2  # makes the first trial step about 1/|g| long (as scipy)
    for _ in range(maxiter):
        if np.max(np.abs(g)) < gtol:
            return x, "converged"
        p = -(H @ g) if H is not None else -g
        alpha, _, _, f_new, _, g_new = search(p, f, g, old_old_f)
        if alpha is None and H is not None:  # a stale curvature model: restart from steepest descent
            H = None
            p = -g
            alpha, _, _, f_new, _, g_new = search(p, f, g, old_old_f)
        if alpha is None:
            return x, "converged"
        s = alpha * p
        x = x + s
        if g_new is None:
            g_new = cached.g(x)
        y = g_new - g
        old_old_f, f, g = f, f_new, g_new
        ys = float(y @ s)
        if ys > 1e-12 * np.linalg.norm(y) * np.linalg.norm(s):
            if H is None:
                H = np.asfortranarray(np.eye(x.size) * (ys / float(y @ y)))
            rho = 1.0 / ys
            Hy = H @ y
            # H <- H - rho (Hy s^T + s Hy^T) + (rho^2 y^T H y + rho) s s^T
            H = dger(-rho, Hy, s, a=H, overwrite_a=True)
            H = dger(-rho, s, Hy, a=H, overwrite_a=True)
            H = dger(rho * rho * float(y @ Hy) + rho, s, s, a=H, overwrite_a=True)
        if callback is not None:
            callback(x)
    return x, "iteration limit"


def _check_surfaces(surfaces):
    surfaces = list(surfaces)
    if not surfaces:
        raise ValueError("fit needs at least one initial surface")
    for k, s in enumerate(surfaces):
        if not isinstance(s, SubdivisionSurface):
            raise TypeError(f"initial surface {k} is a {type(s).__name__}, not a SubdivisionSurface")
    return surfaces


def _objective_call(projector, data):
    if data is None:
        if not hasattr(projector, "job_id"):
            raise ValueError("data is required with a local projector (a remote job holds its own)")
        return lambda surfaces: projector.objective(surfaces)
    return lambda surfaces: projector.objective(surfaces, data)


#: Iterations over which :func:`fit`'s ``rtol`` compares the objective.
STALL_ITERATIONS = 5


def fit(projector, surfaces, data=None, iterations=80, *, method="auto", progress=True, callback=None,
        catch_interrupt=True, penalty=None, label="BubSub fit", rtol=None, rtol_window=STALL_ITERATIONS):
    """Fit bubble surfaces to projections: minimise ``0.5 ||Proj(S x) - d||^2`` over x.

    Parameters
    ----------
    projector : MeshProjector or RemoteJob
        Anything with ``objective(surfaces, data) -> (f, grads)``.
    surfaces : sequence of SubdivisionSurface
        Initial bubbles; their topology and attenuation are kept.
    data : ndarray, optional
        Projections to fit, ``projector.geometry.shape`` (background already
        subtracted). Omit for a remote job, which holds its data.
    iterations : int
        Maximum optimiser iterations (the paper uses 80).
    method : {"auto", "bfgs", "lbfgs"}
        ``auto`` is dense BFGS up to 6000 unknowns (2000 control vertices),
        L-BFGS beyond, where an n x n inverse Hessian no longer fits.
    progress : bool
        Show progress (:func:`bubsub.clients.progress.phase`: a bar on a
        terminal, one summary line with the stop reason otherwise).
    label : str
        The progress line's name.
    callback : callable, optional
        Called after each iteration with ``(iteration, objective, surfaces)``;
        return a true value to stop: a string is the stop reason the fit
        reports (in plain words, e.g. ``"stopped: ..."``), True reports
        ``"stopped early"``.
    catch_interrupt : bool
        True: Ctrl-C stops the fit and it returns the best iterate so far,
        flagged ``interrupted`` (the ``bubsub reconstruct`` command then
        writes it); before the first evaluation has finished there is none
        and the KeyboardInterrupt propagates. False: the KeyboardInterrupt propagates, for fits inside
        a larger computation (topology rounds, repairs) that must stop too.
    penalty : callable, optional
        ``penalty(vertex_sets) -> (value, grads)`` on the control vertices of
        all bubbles (a list of ``(n_k, ndim)`` arrays; ``grads`` alike), added
        to the objective, e.g. :func:`bubsub.clients.optimise.separation.separation_penalty`.
    rtol : float, optional
        Converged when the objective fell by less than ``rtol`` times its
        value over the last ``rtol_window`` iterations (L-BFGS on thousands
        of unknowns otherwise runs to ``iterations``: its gradient test never
        triggers on noisy data).
    rtol_window : int
        Default :data:`STALL_ITERATIONS`.

    Returns
    -------
    FitResult

    Notes
    -----
    On few cores, idle BLAS threads spinning after each small matrix product
    take the cores the ray casting needs; fits run up to twice as fast with
    ``threadpoolctl.threadpool_limits(1, "blas")`` around them (the ``bubsub``
    command does this for its whole process).
    """
    surfaces = _check_surfaces(surfaces)
    if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) or iterations < 0:
        raise ValueError(f"iterations must be a non-negative integer, got {iterations!r}")
    evaluate = _objective_call(projector, data)
    shapes = [s.vertices.shape for s in surfaces]
    splits = np.cumsum([int(np.prod(sh)) for sh in shapes])[:-1]
    x0 = np.concatenate([s.vertices.ravel() for s in surfaces])
    if method == "auto":
        method = "bfgs" if x0.size <= DENSE_BFGS_LIMIT else "lbfgs"
    if method not in ("bfgs", "lbfgs"):
        raise ValueError(f"method must be 'auto', 'bfgs' or 'lbfgs', got {method!r}")

    def unpack(x):
        return [s.with_vertices(p.reshape(sh)) for s, p, sh in zip(surfaces, np.split(x, splits), shapes)]

    best = {"f": np.inf, "x": x0, "evals": 0, "penalty": 0.0}
    t0 = time.perf_counter()

    def fun(x):
        items = unpack(x)
        f, grads = evaluate(items)
        p = 0.0
        if penalty is not None:
            p, extra = penalty([s.vertices for s in items])
            f = f + p
            grads = [np.asarray(g) + e for g, e in zip(grads, extra)]
        best["evals"] += 1
        if f < best["f"]:
            best["f"], best["x"], best["penalty"] = f, x.copy(), p
        return f, np.concatenate([np.asarray(g).ravel() for g in grads])

    history = []
    bar = phase(label, iterations, enabled=progress)

    class _Stop(Exception):
        def __init__(self, reason):
            super().__init__(reason)
            self.reason = reason

    class _Stalled(Exception):
        pass

    def on_iteration(xk):
        history.append({"iteration": len(history) + 1, "objective": best["f"], "seconds": time.perf_counter() - t0})
        bar.update(1, f=f"{best['f']:.4g}")
        stop = callback(len(history), best["f"], unpack(best["x"])) if callback is not None else None
        if stop:
            raise _Stop(stop if isinstance(stop, str) else "stopped early")
        k = rtol_window
        if rtol is not None and len(history) > k and \
                history[-k - 1]["objective"] - best["f"] <= rtol * best["f"]:
            raise _Stalled

    interrupted = False
    reason = "iteration limit"
    try:
        if iterations == 0:
            fun(x0)
        elif method == "bfgs":
            _, reason = bfgs(fun, x0, int(iterations), callback=on_iteration)
        else:
            options = {"maxiter": int(iterations), "maxcor": 20, "ftol": 1e-15, "gtol": 1e-12,
                       "maxfun": 4 * int(iterations) + 20}
            res = minimize(fun, x0, jac=True, method="L-BFGS-B", callback=on_iteration, options=options)
            reason = _lbfgs_reason(res, len(history), iterations)
    except KeyboardInterrupt:
        interrupted, reason = True, "interrupted"
        if not catch_interrupt:
            raise
    except _Stop as why:
        reason = why.reason
    except _Stalled:
        reason = "converged"
    finally:
        bar.close(reason)
    if not np.isfinite(best["f"]):  # Ctrl-C before the first evaluation finished: nothing to return
        raise KeyboardInterrupt
    return FitResult(
        surfaces=unpack(best["x"]),
        objective=float(best["f"]),
        iterations=len(history),
        evaluations=best["evals"],
        seconds=time.perf_counter() - t0,
        history=history,
        interrupted=interrupted,
        method=method,
        stop_reason=reason,
        penalty=float(best["penalty"]),
    )


def _lbfgs_reason(res, done, limit):
    if done >= limit:
        return "iteration limit"
    if res.status == 1:  # scipy: the evaluation or iteration budget ran out
        return "evaluation limit"
    return "converged"


def estimate_radii(projector, surfaces, data=None, iterations=20, *, ftol=1e-4, progress=False,
                   label="radius estimation"):
    """Improve an initial guess by optimising one radius per bubble (paper eq. 4-5).

    Each bubble keeps its centre (the mean of its control vertices) and its
    shape; only the scale ``r_k`` of ``x_k(r) = c_k + r_k u_k`` changes, with
    ``dg/dr_k = sum_i grad_x_ki . u_ki``. At most ``iterations + 5``
    objective evaluations (each one projection) are made; the search stops
    earlier once an iteration lowers the objective by less than ``ftol``
    (relative), since the full fit refines the radii anyway. Each radius
    stays within ``[0.001, 3]`` times its initial value: the preview's radii
    are within a factor of two, and a first line-search step to ten times
    the radius (the bound before) cost as much as ten evaluations.

    Returns
    -------
    list of SubdivisionSurface
    """
    surfaces = _check_surfaces(surfaces)
    evaluate = _objective_call(projector, data)
    centres = [s.vertices.mean(axis=0) for s in surfaces]
    r0 = np.array([np.linalg.norm(s.vertices - c, axis=1).mean() for s, c in zip(surfaces, centres)])
    units = [(s.vertices - c) / r for s, c, r in zip(surfaces, centres, r0)]

    def build(r):
        return [s.with_vertices(c + rk * u) for s, c, rk, u in zip(surfaces, centres, r, units)]

    # scipy's maxfun is only checked between iterations, so a line search can run past it:
    # stop at the cap here, and return the best radii seen
    cap = int(iterations) + 5
    best = {"f": np.inf, "r": r0, "evals": 0}

    class _Budget(Exception):
        pass

    def fun(r):
        if best["evals"] >= cap:
            raise _Budget
        best["evals"] += 1
        f, grads = evaluate(build(r))
        if f < best["f"]:
            best["f"], best["r"] = f, r.copy()
        return f, np.array([np.sum(np.asarray(g) * u) for g, u in zip(grads, units)])

    with phase(label, iterations, enabled=progress) as bar:
        try:
            res = minimize(fun, r0, jac=True, method="L-BFGS-B", bounds=[(1e-3 * r, 3 * r) for r in r0],
                           callback=lambda _: bar.update(1),
                           options={"maxiter": int(iterations), "maxfun": cap, "ftol": float(ftol)})
            reason = _lbfgs_reason(res, bar.n, iterations)
        except _Budget:
            reason = "evaluation limit"
        bar.close(reason)
    return build(best["r"])
