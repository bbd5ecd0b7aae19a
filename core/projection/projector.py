"""Exact X-ray projection of closed meshes, and its gradient: the public :class:`MeshProjector`.

Each detector pixel's value is the sum over meshes of ``attenuation x (length
of the ray inside the mesh)``. How the crossings of rays and faces are found is
a backend's business (:mod:`bubsub.core.projection.backends`: the exact
triangle-major ``raster`` backend, and the Embree ray casters ``native`` and
``embreex``); this module resolves the items, checks inputs, averages
sub-rays, forms the residual and chains the gradient back to each item's own
vertices, once for all backends.

Gradient: moving vertex ``i`` of a crossed triangle by ``dv`` changes the
crossing distance by ``b_i n.dv / (n.d)``; entering crossings count negative,
so the chord's derivative is ``b_i n / |n.d|`` for both (``b_i`` barycentric
weight, ``n`` unit normal, ``d`` unit ray direction).

Every operator takes an optional ``deadline`` (a :func:`time.monotonic`
value): past it the work stops within milliseconds (the compiled kernels read
a stop flag every few thousand rays, the steps in Python check the clock) and
the call raises :class:`DeadlineExceeded` (a ``TimeoutError``); a server
bounds each computation this way.
"""

from __future__ import annotations

import os

import numpy as np

from bubsub.core.projection.backends import select
from bubsub.core.projection.backends.base import DeadlineExceeded, Scene, Traversal, check_deadline, vertex_gradient
from bubsub.core.projection.backends.frames import Frames
from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.projection.mesh import Mesh, Polygon
from bubsub.core.projection.subdivision import SubdivisionSurface
from bubsub.core.threads import thread_map
from bubsub.core.validate import check_int

__all__ = ["MeshProjector", "Traversal", "DeadlineExceeded", "default_threads"]


#: pixels per block of the forward's averaging (:meth:`MeshProjector._projection`)
PROJECTION_BLOCK = 1 << 22


def default_threads():
    """Threads of a projector made without ``threads``: ``BUBSUB_THREADS``, else the usable cores.

    A Dask worker sets ``BUBSUB_THREADS`` so that its tasks share the machine
    with the other workers' instead of each taking every core.
    """
    text = os.environ.get("BUBSUB_THREADS", "").strip()
    if text:
        if not text.isdigit() or int(text) < 1:
            raise ValueError(f"BUBSUB_THREADS must be a positive integer, got {text!r}")
        return int(text)
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _threaded_residual(kernel, values, k2, data, out, threads):
    """``kernel`` (:func:`~bubsub.core.projection.backends.common_kernels.residual`) over contiguous chunks,
    one per thread, and the sum of their ``f`` (serial, it would be 3 ms of every evaluation on a
    25 x 256 x 512 scan). Small scans take one chunk."""
    n = values.shape[0]
    parts = max(1, min(int(threads), n // (1 << 18)))
    edges = np.linspace(0, n, parts + 1).round().astype(int)
    chunks = [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]
    return float(sum(thread_map(lambda c: kernel(values[c[0]:c[1]], k2, data[c[0]:c[1]], out[c[0]:c[1]]),
                                chunks, parts)))


class MeshProjector:
    """Exact projector of closed meshes for one scan geometry.

    Parameters
    ----------
    geometry : ScanGeometry
    supersampling : int
        ``k``: ``k x k`` rays per pixel (``k`` in 2D), averaged, modelling
        the finite pixel width.
    threads : int, optional
        Worker threads; defaults to :func:`default_threads` (``BUBSUB_THREADS``,
        else the usable cores).
    backend : {"auto", "raster", "native", "embreex"}
        How crossings are found; all are exact and agree.
        ``"raster"``: triangle-major, float64, numba (the fastest).
        ``"native"``: Embree 4 from compiled code, all of a ray's crossings
        in one traversal. ``"embreex"``: embreex's closest-hit casts, once
        per crossing. ``"auto"`` takes the environment variable
        ``BUBSUB_BACKEND`` when set, else the fastest available
        (:func:`bubsub.core.projection.backends.select`).

    Notes
    -----
    Items to project are :class:`Mesh` (3D), :class:`Polygon` (2D) or
    :class:`SubdivisionSurface`; gradients are with respect to each item's own
    vertices (the control vertices of a subdivision surface). Projections are
    float32 of shape ``geometry.shape``; lengths in mm, attenuation in 1/mm.
    Cone and fan beams need every vertex in front of the source.
    """

    def __init__(self, geometry, supersampling=1, threads=None, backend="auto"):
        self._backend = select(backend)
        self.backend = self._backend.name
        if not isinstance(geometry, ScanGeometry):
            raise TypeError(f"geometry must be a ScanGeometry, got {type(geometry).__name__}")
        check_int(supersampling, "supersampling", 1, 16)
        self.geometry = geometry
        self.supersampling = int(supersampling)
        if threads is None:
            threads = default_threads()
        self.threads = max(1, int(threads))
        self._frames = Frames(geometry)
        k = self.supersampling
        off = (np.arange(k) + 0.5) / k - 0.5
        if geometry.ndim == 3:
            self._sub = np.stack([np.repeat(off, k), np.tile(off, k)], axis=1)
        else:
            self._sub = np.stack([off, np.zeros(k)], axis=1)

    @property
    def range_shape(self):
        """Shape of the projections, ``geometry.shape``."""
        return self.geometry.shape

    def __repr__(self):
        return f"MeshProjector({self.geometry!r}, supersampling={self.supersampling}, backend={self.backend!r})"

    # -- public operators -----------------------------------------------------------
    def forward(self, meshes, deadline=None):
        """Projections of ``meshes``: float32 array of ``geometry.shape``.

        ``deadline`` (all operators): :func:`time.monotonic` value past which
        the work stops, with :class:`DeadlineExceeded`.
        """
        return self._projection(self.trace(meshes, deadline), deadline)

    def vjp(self, meshes, residual, deadline=None):
        """Gradient of ``<forward(meshes), residual>`` with respect to each item's vertices.

        Parameters
        ----------
        meshes : sequence of Mesh, Polygon or SubdivisionSurface
        residual : array of ``geometry.shape``
        deadline : float, optional

        Returns
        -------
        list of (n_i, 3) or (n_i, 2) float
        """
        r = self._check_array(residual, "residual")
        scene = self._scene(meshes, deadline)
        return self._gradient(scene, self._trace(scene, gradient=True, deadline=deadline), r)

    def objective(self, meshes, data, deadline=None):
        """``f = 0.5 ||forward(meshes) - data||^2`` and its gradient, from one traversal.

        Returns
        -------
        f : float
        grads : list of (n_i, 3) or (n_i, 2) float
        """
        from bubsub.core.projection.backends.common_kernels import residual as residual_kernel

        # NaN or inf in the data makes f non-finite; the full check then names it (checking every
        # value first cost a pass over the data at every evaluation of a fit)
        d = self._check_array(data, "data", finite=False)
        scene = self._scene(meshes, deadline)
        flat = d.ravel() if d.dtype in (np.float32, np.float64) else d.ravel().astype(np.float64)
        # view by view where the backend can: the crossings of a few views fit its store, those of the
        # whole scan may not (the gradient then rasterised every view again)
        fused = self._backend.objective(scene, self._frames, self._sub, self.threads, flat, deadline)
        if fused is not None:
            f, sums = fused
            if not np.isfinite(f):
                self._check_array(data, "data")
            return f, scene.item_gradients(vertex_gradient(scene, sums))
        traversal = self._trace(scene, gradient=True, deadline=deadline)
        # the float32 projection is what forward() returns; f and the gradient use it too
        values = traversal.values
        # the residual overwrites the traversal's values (never read again): no fresh 8-byte-per-pixel array
        residual = values if values.dtype == np.float64 and values.flags.writeable else np.empty(d.size)
        f = _threaded_residual(residual_kernel, values, float(self._sub.shape[0]), flat, residual, self.threads)
        if not np.isfinite(f):
            self._check_array(data, "data")
        return f, self._gradient(scene, traversal, residual)

    def trace(self, meshes, deadline=None):
        """Find every crossing once: the backend's :class:`Traversal` (values and crossing count)."""
        return self._trace(self._scene(meshes, deadline), deadline=deadline)

    # -- internals ----------------------------------------------------------------
    def _scene(self, meshes, deadline=None):
        if isinstance(meshes, (Mesh, Polygon, SubdivisionSurface)):
            meshes = [meshes]
        scene = Scene(meshes, self.geometry.ndim, self._backend.prisms_2d, self.threads)
        self._frames.check_scene(scene)
        check_deadline(deadline)  # the fine meshes took their time: stop before tracing
        return scene

    def _trace(self, scene, gradient=False, deadline=None):
        return self._backend.trace(scene, self._frames, self._sub, self.threads, gradient, deadline)

    def _check_array(self, a, name, finite=True):
        if not isinstance(a, np.ndarray):
            a = np.asarray(a)
        if a.shape != self.range_shape:
            raise ValueError(f"{name} must have shape {self.range_shape} (geometry.shape), got {a.shape}")
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise ValueError(f"{name} must be a real float array, got dtype {a.dtype}")
        if finite and not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contains NaN or inf")
        return a  # not cast here: a float32 data set is used as it is, without a float64 copy per call

    def _projection(self, traversal, deadline=None):
        """The float32 projection: the traversal's sums over ``k^2`` sub-rays averaged, in one pass per
        block of :data:`PROJECTION_BLOCK` pixels (the deadline checked before each: 31 million pixels
        take a few tenths of a second)."""
        k2 = self._sub.shape[0]
        values = traversal.values
        out = np.empty(values.shape, np.float32)
        for a in range(0, values.size, PROJECTION_BLOCK):
            check_deadline(deadline)
            b = a + PROJECTION_BLOCK
            if k2 > 1:  # float64 quotient rounded to float32, as (values / k2).astype(float32)
                np.divide(values[a:b], k2, out=out[a:b], casting="unsafe")
            else:
                out[a:b] = values[a:b]
        check_deadline(deadline)
        return out.reshape(self.range_shape)

    def _gradient(self, scene, traversal, residual):
        k2 = self._sub.shape[0]
        w = residual.ravel() / k2 if k2 > 1 else residual.ravel().astype(np.float64, copy=False)
        try:
            sums = traversal.face_sums(w)
        finally:
            traversal.release()
        return scene.item_gradients(vertex_gradient(scene, sums))
