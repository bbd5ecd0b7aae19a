"""The interface between :class:`~bubsub.core.MeshProjector` and its backends.

A backend receives a :class:`Scene` (every item's fine mesh as one shifted
triangle soup, or one segment soup in 2D) and the scan's :class:`Frames`, and
returns a :class:`Traversal`: the per-pixel values and a way to reduce the
crossings it found against per-pixel weights (``face_sums``). Everything else
lives once, in the projector and here: resolving items, the chain rule through
the subdivision matrices, the residual, the gradient's per-vertex scatter.

Adding a backend means writing one class with ``name``, ``prisms_2d`` and
``trace(scene, frames, sub, threads)`` and registering it in
:mod:`bubsub.core.projection.backends`; the objective, the subdivision chain
and the service do not change.

The gradient contract
---------------------
For a closed outward mesh the chord of a ray is ``sum_exits t - sum_entries t``.
Moving vertex ``j`` of a crossed face ``f`` by ``dv`` changes it by
``b_j n_f.dv / |n_f.d|`` (``b_j`` barycentric weight of the crossing, ``n_f``
the unit normal, ``d`` the unit ray direction). ``face_sums(w)`` returns, per
face and corner, ``sum over crossings of w[pixel] mu_f b_j / |n_f.d|``; the
projector multiplies by ``n_f`` and scatters to the vertices.

Deadlines
---------
A call may carry a ``deadline`` (a :func:`time.monotonic` value). A backend
turns it into a stop flag (:func:`stop_flag`: one byte, set by a watchdog
thread the moment the deadline passes) that its compiled loops read every
few thousand rays, so that work past the deadline ends within milliseconds
whatever the call's shape (one view of many rays, or many views); pieces of
work in Python check the clock (:func:`check_deadline`) between steps. A
kernel that sees the flag returns what it has, and the backend then raises
:class:`DeadlineExceeded`; every thread stops at its next check, and the
exception is raised once all have (:func:`deadline_map`). Without a deadline
the flag is never set and the results are the same to the bit.
"""

from __future__ import annotations

import heapq
import itertools
import os
import threading
import time
import weakref

import numpy as np

from bubsub.core.projection.mesh import Mesh, Polygon, bounding_box
from bubsub.core.projection.subdivision import SubdivisionSurface, control_gradients, fine_vertices
from bubsub.core.threads import thread_map

__all__ = ["Scene", "Traversal", "StoredCrossings", "Backend", "vertex_gradient", "DeadlineExceeded",
           "check_deadline", "stop_flag", "deadline_map"]


class DeadlineExceeded(TimeoutError):
    """A projection stopped at its deadline."""


def check_deadline(deadline):
    """Raise :class:`DeadlineExceeded` once :func:`time.monotonic` has passed ``deadline`` (None: never)."""
    if deadline is not None and time.monotonic() >= deadline:
        raise DeadlineExceeded(f"projection stopped at its deadline ({time.monotonic() - deadline:.3f} s past it)")


class _Watchdog:
    """One daemon thread that sets each registered stop flag when its deadline passes.

    Flags are held weakly: a flag whose computation ended (and dropped it)
    before its deadline costs nothing more than its place in the heap,
    which is cleared of such places whenever it has doubled. A forked child
    starts afresh (its parent's thread does not exist there).
    """

    def __init__(self):
        self._reset()

    def _reset(self):
        self._cond = threading.Condition()
        self._heap = []  # (deadline, sequence number, weak reference to the flag)
        self._order = itertools.count()
        self._limit = 1024  # heap size at which the places of flags already gone are dropped
        self._started = False

    def add(self, deadline, flag):
        with self._cond:
            if not self._started:
                threading.Thread(target=self._serve, args=(self._cond, self._heap), name="bubsub-deadlines",
                                 daemon=True).start()
                self._started = True
            if len(self._heap) >= self._limit:
                self._heap[:] = [e for e in self._heap if e[2]() is not None]
                heapq.heapify(self._heap)
                self._limit = max(1024, 2 * len(self._heap))
            heapq.heappush(self._heap, (deadline, next(self._order), weakref.ref(flag)))
            self._cond.notify()

    @staticmethod
    def _serve(cond, heap):
        with cond:
            while True:
                now = time.monotonic()
                while heap and heap[0][0] <= now:
                    flag = heapq.heappop(heap)[2]()
                    if flag is not None:
                        flag[0] = 1
                cond.wait(heap[0][0] - now if heap else None)


_WATCHDOG = _Watchdog()
if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_WATCHDOG._reset)


def stop_flag(deadline):
    """``(1,) uint8`` array that becomes 1 once :func:`time.monotonic` passes ``deadline`` (None: never).

    The compiled kernels read it every few thousand rays and return early
    when it is set; the caller then raises :class:`DeadlineExceeded`
    (:func:`check_deadline`). It is set by a watchdog thread, so reading it
    costs a load, not a clock call; a flag is kept until its deadline only
    while its caller holds it.
    """
    flag = np.zeros(1, np.uint8)
    if deadline is not None:
        if time.monotonic() >= deadline:
            flag[0] = 1
        else:
            _WATCHDOG.add(float(deadline), flag)
    return flag


def deadline_map(fn, items, threads):
    """:func:`~bubsub.core.threads.thread_map` that, when an item stops at its deadline, waits for the
    others to stop too (each at its next check) before raising :class:`DeadlineExceeded`."""

    def guarded(item):
        try:
            return fn(item)
        except DeadlineExceeded as exc:
            return exc

    out = thread_map(guarded, items, threads)
    for r in out:
        if isinstance(r, DeadlineExceeded):
            raise r
    return out


class Scene:
    """All items to project as one soup, shifted so its bounding box is centred on the origin.

    Attributes
    ----------
    items : list
        What was given (Mesh, Polygon or SubdivisionSurface).
    fine_counts : list of int
        Vertices of each item's projected (fine) mesh or polygon.
    vertices : (n, 3) float
        All vertices minus ``centre``, mm (2D: z = 0, or prism walls).
    faces : (m, 3) int32 or (m, 2) int32
        Triangles, or polygon segments (2D without prisms), into ``vertices`` (int64 from 2^31
        vertices on).
    centre : (3,) float
        The shift, mm.
    half : (3,) float
        Half-sizes of the bounding box, mm.
    face_item : (m,) int64
        Item of each face.
    mu : (n_items,) float
        Attenuation of each item, 1/mm.
    normals : (m, 3) float
        Unit outward normals (2D segments: in the plane z = 0).
    offsets : (m,) float
        ``normals . x0`` for a vertex ``x0`` of each face, mm: the face's plane (line in 2D),
        in the shifted frame.
    vertex_offset : (n_items + 1,) int
        First vertex of each item.
    face_offset : (n_items + 1,) int
        First face of each item (an item's faces use only its own vertices).
    threads : int
        Worker threads for the scene's own per-face steps (planes, gradient scatter).
    """

    def __init__(self, items, ndim, prisms_2d, threads=1):
        self.items = list(items)
        self.ndim = ndim
        expected = Mesh if ndim == 3 else Polygon
        for k, item in enumerate(self.items):
            kind = item.control if isinstance(item, SubdivisionSurface) else item
            if not isinstance(kind, expected):
                raise TypeError(
                    f"item {k} is a {type(item).__name__} of {type(kind).__name__}; "
                    f"a {ndim}D geometry projects {expected.__name__} or SubdivisionSurface of {expected.__name__}"
                )
        if not self.items:
            raise ValueError("nothing to project: give at least one mesh")
        # every item's fine vertices; surfaces that share a topology in one sparse product
        self.threads = max(1, int(threads))
        fine = fine_vertices(self.items, self.threads)
        self.fine_counts = [len(v) for v in fine]
        self.prisms = ndim == 2 and prisms_2d
        if ndim == 3:
            verts = fine
            # the objects a topology keeps (np.asarray would be a new view)
            faces = [it._topo.fine_faces if isinstance(it, SubdivisionSurface) else it.faces for it in self.items]
        elif self.prisms:
            # Short walls (about one edge long) keep the triangles well shaped
            # for Embree's BVH; rays run at z = 0, so any height is exact.
            edges = np.concatenate([np.linalg.norm(np.diff(p, axis=0, append=p[:1]), axis=1) for p in fine])
            self.half_height = max(float(np.median(edges)), 1e-6)
            verts, faces = zip(*(_prism(p, self.half_height) for p in fine))
        else:
            verts = [np.c_[p, np.zeros(len(p))] for p in fine]
            faces = [np.stack([np.arange(len(p)), np.roll(np.arange(len(p)), -1)], 1) for p in fine]
        # 3D faces are objects the items keep (worth caching); 2D ones were just built
        self.faces, self.face_item, self.vertex_offset, self.face_offset = _joined_faces(
            faces, [len(v) for v in verts], cache=ndim == 3)
        vertices = np.concatenate(verts).astype(np.float64, copy=False)
        self.mu = np.array([it.attenuation for it in self.items], dtype=float)
        lo, hi = bounding_box(vertices)
        self.centre = 0.5 * (lo + hi)
        vertices -= self.centre  # in place: a fresh 6 MB array at 256,000 vertices cost its page faults
        self.vertices = vertices
        self.half = 0.5 * (hi - lo)
        if self.prisms:
            self.half[2] = self.half_height
        v, f = self.vertices, self.faces
        if f.shape[1] == 3:
            from bubsub.core.projection.backends.common_kernels import triangle_planes

            self.normals, self.offsets = np.empty((len(f), 3)), np.empty(len(f))
            thread_map(lambda span: triangle_planes(v, f[span[0]:span[1]], self.normals[span[0]:span[1]],
                                                    self.offsets[span[0]:span[1]]),
                       self.face_spans(), self.threads)
        else:  # outward normal of a counter-clockwise polygon's segment: the edge turned clockwise
            e = v[f[:, 1]] - v[f[:, 0]]
            n = np.stack([e[:, 1], -e[:, 0], np.zeros(len(e))], axis=1)
            norm = np.sqrt(np.einsum("ij,ij->i", n, n))[:, None]
            self.normals = np.divide(n, norm, out=n, where=norm > 0)
            self.offsets = np.einsum("ij,ij->i", self.normals, v[f[:, 0]])

    def item_spans(self, parts):
        """Up to ``parts`` ranges ``(first item, end item)`` of about equal numbers of faces, in order,
        covering every item: work split by items touches disjoint vertices and faces."""
        n = len(self.face_offset) - 1
        cuts = np.searchsorted(self.face_offset, np.linspace(0, self.face_offset[-1], max(1, parts) + 1)[1:-1])
        bounds = [0, *sorted({int(c) for c in cuts} - {0, n}), n]
        return list(zip(bounds[:-1], bounds[1:]))

    def face_spans(self):
        """:meth:`item_spans` for :attr:`threads` as face ranges ``(first face, end face)``; one range
        below :data:`THREADED_FACES` faces, where handing work to a thread costs more than it saves."""
        parts = self.threads if self.face_offset[-1] >= THREADED_FACES else 1
        return [(int(self.face_offset[a]), int(self.face_offset[b])) for a, b in self.item_spans(parts)]

    def item_gradients(self, vertex_grad):
        """Split per-vertex gradients into one array per item (chain S and the prism)."""
        fine = []
        for k in range(len(self.items)):
            g = vertex_grad[self.vertex_offset[k]: self.vertex_offset[k + 1]]
            if self.ndim == 2:
                n = self.fine_counts[k]
                g = g[:n, :2] + g[n:, :2] if self.prisms else g[:, :2]
            fine.append(g)
        return control_gradients(self.items, fine, self.threads)


# faces from which a scene's own per-face steps (planes, the gradient's scatter) use its threads:
# about 2 ms of work at 100,000 faces, against some 0.1-0.2 ms to hand work to the pool and wait
THREADED_FACES = 100_000

_JOINED_LOCK = threading.Lock()
_JOINED = []  # the last few (face arrays, counts) -> joined faces; an optimiser projects one topology many times


def _joined_faces(faces, counts, cache=True):
    """All items' faces as one array into the joined vertices, each face's item, and each item's first
    vertex and first face.

    Cached on the identity of the face arrays (a subdivision surface keeps
    its fine faces, a Mesh its faces) and the vertex counts: a fit projects
    the same topology at every evaluation. ``cache=False`` for faces built
    for this call only (2D), which would only push the others out.
    """
    key = tuple(id(f) for f in faces) + tuple(counts)
    if cache:
        with _JOINED_LOCK:
            for _, k, value in _JOINED:
                if k == key:
                    return value
    offset = np.concatenate([[0], np.cumsum(counts)])
    sizes = [len(f) for f in faces]
    face_item = np.repeat(np.arange(len(faces)), sizes)
    face_offset = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    # int32 while the indices fit: a projection reads every face's corners once per view, and
    # half the bytes cost the raster backend 4 % at 512,000 faces (Embree wants 32 bits anyway)
    index = np.int32 if offset[-1] < 2**31 else np.int64
    joined = np.concatenate([np.asarray(f) + o for f, o in zip(faces, offset[:-1])]).astype(index, copy=False)
    value = (joined, face_item, offset, face_offset)  # shared by the scenes of one topology: never written to
    if cache:
        with _JOINED_LOCK:
            _JOINED.insert(0, (list(faces), key, value))  # holding the arrays keeps their ids from being reused
            del _JOINED[4:]
    return value


def _prism(poly, h):
    """Side walls of the polygon extruded to z in [-h, h], outward oriented."""
    n = len(poly)
    v = np.concatenate([np.c_[poly, np.full(n, -h)], np.c_[poly, np.full(n, h)]])
    i = np.arange(n)
    j = (i + 1) % n
    faces = np.concatenate([np.stack([i, j, j + n], 1), np.stack([i, j + n, i + n], 1)])
    return v, faces


def vertex_gradient(scene, face_sums):
    """Per-vertex gradient (n, 3) from per-face, per-corner sums (m, k) (see the module docstring)."""
    from bubsub.core.projection.backends.common_kernels import scatter_face_sums

    out = np.zeros((len(scene.vertices), 3))
    sums = np.ascontiguousarray(face_sums, dtype=np.float64)
    # by items, whose faces use only their own vertices: no two threads add to one vertex
    thread_map(lambda span: scatter_face_sums(scene.faces[span[0]:span[1]], sums[span[0]:span[1]],
                                              scene.normals[span[0]:span[1]], out),
               scene.face_spans(), scene.threads)
    return out


class Traversal:
    """What one pass of a backend over a scene found.

    Attributes
    ----------
    values : (n_pixels,) float
        Projection summed over sub-rays (not yet averaged), flat.
    count : int
        Number of valid ray-surface crossings.
    """

    def __init__(self, values, count):
        self.values = values
        self.count = int(count)

    def face_sums(self, weights):
        """``(m, k)`` float: per face and corner, ``sum w[pixel] mu b_j / |n.d|`` over the crossings.

        Parameters
        ----------
        weights : (n_pixels,) float
            Per-pixel weight of every sub-ray (the residual over ``k^2``).
        """
        raise NotImplementedError

    def release(self):
        """Hand back any working memory: the projector calls it once the gradient is taken
        (``face_sums`` may not be called afterwards). Nothing by default."""


class StoredCrossings(Traversal):
    """A traversal whose crossings are kept, in the work chunks that found them (ray-casting backends).

    Attributes
    ----------
    chunks : list of tuple
        Per chunk: ``pixel (k,) int64``, ``face (k,) int32``,
        ``bary (k, 3) float32``, ``inv_cos (k,) float32`` (``1 / |n.d|``).
    """

    def __init__(self, values, chunks, scene, pool_map, deadline=None):
        super().__init__(values, sum(c[0].size for c in chunks))
        self.chunks = chunks
        self._scene = scene
        self._map = pool_map
        self._deadline = deadline

    def face_sums(self, weights):
        scene = self._scene
        mu = scene.mu[scene.face_item]
        nf = len(scene.faces)

        def per_chunk(chunk):
            check_deadline(self._deadline)
            # n is constant on a face, so sum b_j * coef per face first
            pixel, face, bary, inv_cos = chunk
            coef = weights[pixel] * inv_cos * mu[face]
            return np.stack([np.bincount(face, weights=coef * bary[:, j], minlength=nf) for j in range(3)], axis=1)

        return sum(self._map(per_chunk, self.chunks), np.zeros((nf, 3)))


class Backend:
    """A way to find the crossings of a scene's rays with its faces.

    Attributes
    ----------
    name : str
        The name ``MeshProjector(backend=...)`` and ``BUBSUB_BACKEND`` use.
    prisms_2d : bool
        Whether 2D polygons reach :meth:`trace` as prisms of triangles
        (ray casters) or as segments (``faces`` of shape (m, 2)).
    """

    name = ""
    prisms_2d = True

    def trace(self, scene, frames, sub, threads, gradient=False, deadline=None):
        """Cast every sub-ray of every pixel through ``scene``.

        Parameters
        ----------
        scene : Scene
        frames : bubsub.core.projection.backends.frames.Frames
        sub : (k2, 2) float
            Sub-ray offsets in pixel units (``(0, 0)`` without supersampling).
        threads : int
        gradient : bool
            Whether ``face_sums`` will be called (a backend may then keep
            what it found, within a memory bound).
        deadline : float, optional
            :func:`time.monotonic` value past which the work stops within a
            few thousand rays (``face_sums`` keeps it too), with
            :class:`DeadlineExceeded`.

        Returns
        -------
        Traversal
        """
        raise NotImplementedError

    def objective(self, scene, frames, sub, threads, data, deadline=None):
        """``f = 0.5 ||forward - data||^2`` and the face sums of its gradient in one pass, or None.

        A backend that can take the residual view by view, while the crossings
        it just found are still at hand, implements this; None (the default)
        makes the projector trace the whole scan first and call
        :meth:`Traversal.face_sums` after.

        Parameters
        ----------
        scene, frames, sub, threads, deadline
            As :meth:`trace`.
        data : (n_pixels,) float32 or float
            The measured projections, flat.

        Returns
        -------
        (f, sums) or None
            ``f`` float; ``sums`` the ``(m, k)`` face sums of the residual's weights
            (:meth:`Traversal.face_sums`).
        """
        return None

    def __repr__(self):
        return f"{type(self).__name__}()"
