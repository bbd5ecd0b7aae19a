"""The projector's backends: how the crossings of rays with mesh faces are found.

* ``raster`` (:mod:`.raster`): triangle-major, exact and watertight in
  float64, numba; the fastest, and what ``"auto"`` picks.
* ``native`` (:mod:`.embree_native`): ray-major, Embree 4 called from numba,
  all of a ray's crossings from one traversal.
* ``embreex`` (:mod:`.embreex`): ray-major through embreex's closest-hit
  interface, one cast per crossing.

The two Embree backends are an independent engine (float32 rays, a BVH) that
cross-checks the raster backend. The interface all three implement is in
:mod:`.base`; choosing one (argument or ``BUBSUB_BACKEND``) happens only in
:func:`select`.
"""

from __future__ import annotations

import os

__all__ = ["NAMES", "select", "available_backends"]

#: every backend, fastest first
NAMES = ("raster", "native", "embreex")


def _module(name):
    if name == "raster":
        from bubsub.core.projection.backends import raster as m
    elif name == "native":
        from bubsub.core.projection.backends import embree_native as m
    else:
        from bubsub.core.projection.backends import embreex as m
    return m


def _available(name):
    m = _module(name)
    return (True, "") if not hasattr(m, "available") else (m.available(), m.unavailable_reason())


def available_backends():
    """Names of the backends that can run here, fastest first."""
    return [n for n in NAMES if _available(n)[0]]


def select(backend="auto"):
    """The backend object for a name.

    Parameters
    ----------
    backend : {"auto", "raster", "native", "embreex"}
        ``"auto"`` takes the environment variable ``BUBSUB_BACKEND`` when it
        is set (and not "auto"), else the fastest available backend.

    Raises
    ------
    ValueError
        An unknown name (saying whether it came from ``BUBSUB_BACKEND``).
    RuntimeError
        A backend that cannot run here, and why.
    """
    source = "backend"
    if backend == "auto" and os.environ.get("BUBSUB_BACKEND", "auto") != "auto":
        backend, source = os.environ["BUBSUB_BACKEND"], "BUBSUB_BACKEND"
    if backend != "auto" and backend not in NAMES:
        raise ValueError(f"{source} must be 'auto' or one of {', '.join(repr(n) for n in NAMES)}, got {backend!r}")
    if backend == "auto":
        backend = available_backends()[0]
    ok, why = _available(backend)
    if not ok:
        raise RuntimeError(f"the {backend} backend is unavailable: {why}")
    m = _module(backend)
    cls = {"raster": "RasterBackend", "native": "NativeBackend", "embreex": "EmbreexBackend"}[backend]
    return getattr(m, cls)()
