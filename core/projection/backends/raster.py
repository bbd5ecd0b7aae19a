"""The triangle-major (rasterising) backend: exact chords from projected triangles, in numba, float64.

Per projection every vertex is projected onto the detector (centrally for
cone/fan beams, orthographically for parallel beams), in units of the
sub-ray lattice (pixel centres, or the ``k x k`` supersampling points).
Each triangle then visits the lattice points inside its projection; a point
inside means the point's ray crosses the triangle, and the ray's value gets
``mu n.(x0 - q) / |n.d|``: the signed distance along the ray from a fixed
point ``q`` of the ray to the triangle's plane, positive when leaving (n.d > 0)
and negative when entering. Over a closed outward mesh these sum to the chord
whatever ``q`` is; ``q`` is the ray's closest point to the scene centre, so
the terms are about the scene's size and a far source loses no precision.
2D scans do the same with polygon segments on the 1D detector.

Exact and watertight
--------------------
* Everything is float64; a vertex is projected once per projection.
* Each edge's test is computed from its lower-indexed vertex, so the two
  triangles sharing an edge evaluate the same number; they see the edge with
  opposite orientation, and a lattice point exactly on it goes to the one
  triangle whose interior lies on the side of a fixed symbolic perturbation
  of the point (``+e`` along the detector columns, ``+e^2`` along the rows).
  Points on projected vertices are decided by the same perturbation, so a
  fan of triangles around a vertex covers it exactly once. Every ray
  therefore crosses each surface once per side; no pairing is needed.
* In 2D a segment covers the lattice points in ``[min, max)`` of its two
  projected vertices (the same perturbation).
* Cone and fan beams need every vertex in front of the source (projected
  triangles are only meaningful there); the projector refuses other scenes.

Speed
-----
Per projection the vertices are projected once, with the projection's
constants out of the loop. The faces then go in chunks of 256 (never
across an item): their projected vertices are gathered into a small flat
buffer, a branch-free test over its contiguous lanes (vectorised) keeps
the candidates, those whose box holds a lattice point, less those whose
single lattice point is clearly outside (by far more than any rounding),
and sorts them into small ones (boxes of one or two lattice points: most
triangles at fine subdivision), 2 x 2 boxes (about 40 % at two levels of
subdivision) and the others. The small ones, then the 2 x 2 ones, are copied
into contiguous rows of the buffer and their points evaluated in one
vectorised loop without branches (edges, plane, crossing, gradient
coefficients), then their crossings are added; each other candidate
evaluates its box's lattice points without branches, its contributions
selected by the inside test (boxes of more than 96 points skip the points
outside, row by row). The forward pass marks, per projection, one bit per
face that it found crossed (the small triangles' stored crossings only
once the store fills: a full store needs no marks); the gradient pass
visits only those faces.

Gradient
--------
``face_sums`` adds ``w[pixel] mu b_j / |n.d|`` per face corner; ``b_j`` are
the 3D barycentric weights of the crossing, from the 2D ones corrected for
perspective (``b_j ~ lambda_j / depth_j``). When a gradient will follow
(``objective``, ``vjp``), the forward pass keeps each crossing's face, pixel
and three coefficients (32 bytes) within a fixed budget
(:func:`store_bytes`, ``BUBSUB_RASTER_STORE_MB``, default 160 MB), and
``face_sums`` is then one pass over them (a tenth of a rasterisation); a
group of projections whose crossings do not fit, or a plain ``forward``,
keeps nothing and rasterises again. Memory is O(detector + vertices) per
thread plus at most that budget.

Objective
---------
``MeshProjector.objective`` goes view by view instead (:meth:`RasterBackend.objective`):
each thread takes its projections in chunks of as many views as its part of
the store holds (learnt from the chunk before, with a tenth to spare),
rasterises a chunk storing its crossings, takes the chunk's residual in
place, and adds its face sums from the store at once. When a single view's
crossings outgrow a thread's part of the store, the thread takes a store of
its own holding one view (a quarter to spare, at most the whole budget):
otherwise every view of a dense foam, whose single views outgrow a thread's
part, would be rasterised twice. A scan's crossings rarely fit the store (a
slab of a dense column has tens of millions, gigabytes), a few views' always
do: a whole-scan trace would rasterise every view twice, the view-by-view
objective rasterises it once (docs/projector.md measures both on a slab of
``bubsub bench scale``'s column). A chunk that overflows all the same
rasterises again for its face sums. The kernels see a chunk as a scan of its own views, so its
projection needs a buffer of the chunk's pixels only.

Threads: projections are split into contiguous groups, one per worker thread
(compiled code releases the GIL); values are written per projection and face
sums are accumulated per group, then added, so there are no races. Where the
forward pass went item by item and kept every crossing, the face sums are
split among the threads by items instead, into one array (an item's faces
belong to one thread).

Deadline: the kernels read the call's stop flag
(:func:`~bubsub.core.projection.backends.base.stop_flag`) per projection, per
chunk of 256 faces (per face in the gradient pass), per row of a box of
more than 16,384 lattice points and every 16,384 stored crossings, and
return early once the deadline has set it; the backend then raises
:class:`~bubsub.core.projection.backends.base.DeadlineExceeded`. A call
with a deadline makes the same kernel calls as one without, so its results
are the same to the bit.
"""

from __future__ import annotations

import os
import threading

import numpy as np

from bubsub.core.projection.backends.base import Backend, Traversal, check_deadline, deadline_map, stop_flag
from bubsub.core.threads import thread_map

__all__ = ["RasterBackend", "available", "unavailable_reason", "release_stores"]

_state = {}


def _load():
    if "ok" not in _state:
        try:
            _state.update(_compile())
            _state["ok"] = True
        except ImportError as exc:
            _state["ok"], _state["why"] = False, f"numba is not installed ({exc})"
    return _state["ok"]


def available():
    """Whether numba is importable (the backend's only requirement)."""
    return _load()


def unavailable_reason():
    """Why :func:`available` is False ("" when it is True)."""
    return "" if _load() else _state["why"]


class RasterBackend(Backend):
    """Exact triangle-major projection (see the module docstring)."""

    name = "raster"
    prisms_2d = False

    def trace(self, scene, frames, sub, threads, gradient=False, deadline=None):
        if not _load():
            raise RuntimeError(f"the raster backend is unavailable: {unavailable_reason()}")
        job = _Job(scene, frames, sub, threads, store=gradient, deadline=deadline)
        # each group zeroes its own projections (raster3d, view by view): 26 MB of zeros here would be a serial
        # millisecond per call
        values = np.empty(frames.n * frames.rows * frames.cols)
        try:
            counts = deadline_map(lambda g: job.run(g, values, None, None), job.groups, job.threads)
        except BaseException:
            _RasterTraversal(values, 0, job).release()
            raise
        return _RasterTraversal(values, sum(counts), job)

    def objective(self, scene, frames, sub, threads, data, deadline=None):
        """``f`` and its face sums view by view (see "Objective" in the module docstring)."""
        if scene.ndim != 3:
            return None
        if not _load():
            raise RuntimeError(f"the raster backend is unavailable: {unavailable_reason()}")
        job = _Job(scene, frames, sub, threads, store=True, deadline=deadline)
        try:
            parts = deadline_map(lambda g: job.objective(g, data), job.groups, job.threads)
        finally:
            if job.store is not None:
                _give_back(job.store)
        sums = parts[0][1]
        for _, other in parts[1:]:  # in place, as in face_sums
            sums += other
        return float(sum(p[0] for p in parts)), sums


def store_bytes():
    """Most bytes the forward pass may use to store crossings for the gradient: ``BUBSUB_RASTER_STORE_MB``
    (default 160; 0 always rasterises again for the gradient). 32 bytes per crossing."""
    text = os.environ.get("BUBSUB_RASTER_STORE_MB", "").strip()
    if not text:
        return 160 * 2**20
    try:
        mb = float(text)
    except ValueError:
        mb = -1.0
    if not mb >= 0:
        raise ValueError(f"BUBSUB_RASTER_STORE_MB must be a number of megabytes >= 0, got {text!r}")
    return int(mb * 2**20)


#: faces from which the forward pass goes item by item (raster_kernels.raster3d, _Job)
ITEM_MAJOR_FACES = 100_000

_POOL_LOCK = threading.Lock()
_POOL = []  # crossing stores handed back by finished gradients, reused: fresh pages cost a fault each


def _take_store(m):
    """``(face (m,) int32, pixel (m,) int32, coefficients (m, 3) float)``, reused when one is free.

    A full store is 128 MB on the foam3d benchmark; writing it into fresh
    pages costs 19 ms of page faults per objective against 5 ms into pages
    already mapped. At most two stores are kept (one per concurrent fit is
    the common case; a server's further threads allocate their own).
    """
    with _POOL_LOCK:
        for i, store in enumerate(_POOL):
            if store[0].shape[0] == m:
                return _POOL.pop(i)
    return np.empty(m, np.int32), np.empty(m, np.int32), np.empty((m, 3))


def _give_back(store):
    with _POOL_LOCK:
        if len(_POOL) < 2:
            _POOL.append(store)


def release_stores():
    """Drop the crossing stores kept for reuse, so that their pages go back to the system.

    A store stays resident between fits (up to ``BUBSUB_RASTER_STORE_MB``, 160 MB, each): a caller about to
    do memory-heavy work that projects nothing (a voxel preview) lets them go; the next fit allocates a
    store again, its pages faulted in as it fills them.
    """
    with _POOL_LOCK:
        _POOL.clear()


class _RasterTraversal(Traversal):
    def __init__(self, values, count, job):
        super().__init__(values, count)
        self._job = job

    def release(self):
        job, self._job = self._job, None
        if job is not None and job.store is not None:
            _give_back(job.store)

    def face_sums(self, weights):
        job = self._job
        nf, k = job.scene.faces.shape
        if job.by_item_store():
            return self._item_face_sums(weights)

        def group(g):
            acc = np.zeros((nf, k))
            face, pix, coef, n = job.stores[g]
            if n >= 0:  # the forward pass kept this group's crossings
                _state["stored_face_sums"](face, pix, coef, n, weights, acc, *job.ray_lengths, job.stop)
                check_deadline(job.deadline)
            else:
                job.run(g, None, weights, acc)
            return acc

        sums = deadline_map(group, job.groups, job.threads)
        for other in sums[1:]:  # in place: a fresh sum would be two more passes over (faces, 3) per call
            sums[0] += other
        return sums[0]

    def _item_face_sums(self, weights):
        """Face sums from stores kept item by item, split among the threads by items: each thread
        writes only its items' faces of one shared array. Per group, face-sum arrays (12 MB each
        at 512,000 faces) competed for the shared cache and cost a reduction."""
        job = self._job
        check_deadline(job.deadline)
        acc = np.zeros(job.scene.faces.shape)
        # each item's start in the whole store, per chunk of views of every group (rows in view order)
        starts = np.stack([row for g in job.groups for row in job.store_items[g]])

        def items(span):
            _state["item_face_sums"](*job.store, starts, span[0], span[1], weights, acc, *job.ray_lengths, job.stop)

        thread_map(items, job.scene.item_spans(job.threads), job.threads)
        check_deadline(job.deadline)
        return acc


class _Job:
    """Per-projection frames in the scene's shifted coordinates, and the kernel's arguments."""

    def __init__(self, scene, frames, sub, threads, store=False, deadline=None):
        self.scene = scene
        self.deadline = deadline
        self.stop = stop_flag(deadline)  # set when the deadline passes: the kernels then return early
        k2 = sub.shape[0]
        self.k = int(round(np.sqrt(k2))) if scene.ndim == 3 else k2
        shift = scene.centre
        cone = frames.cone
        S = frames.s - shift if cone else frames.s / np.linalg.norm(frames.s, axis=1, keepdims=True)
        D = frames.d - shift
        U, V = frames.u, frames.v
        N = np.cross(U, V)
        vn, nu = np.cross(V, N), np.cross(N, U)
        Au = vn / np.einsum("ij,ij->i", U, vn)[:, None]
        Bv = nu / np.einsum("ij,ij->i", V, nu)[:, None]
        self.frames = tuple(np.ascontiguousarray(a, dtype=np.float64) for a in (S, D, U, V, N, Au, Bv))
        self.cone, self.rows, self.cols = bool(cone), int(frames.rows), int(frames.cols)
        self.ray_lengths = _pixel_ray_lengths(frames, self.stop, deadline) if cone and self.k == 1 and scene.ndim == 3 \
            else (np.ones(1), False)
        f = scene.faces
        self.faces = np.ascontiguousarray(f)  # int32 (Scene), int64 for the largest scenes
        self.normals = np.ascontiguousarray(scene.normals)
        self.offset = scene.offsets
        self.face_mu = scene.mu[scene.face_item].astype(np.float64)
        self.vertices = np.ascontiguousarray(scene.vertices, dtype=np.float64)
        # each item's first vertex and first face: the forward pass goes item by item (raster3d)
        self.item_vertices = np.ascontiguousarray(scene.vertex_offset, dtype=np.int64)
        self.item_faces = scene.face_offset
        # item by item only for scenes whose per-projection data (about 100 bytes a face) outgrows
        # the caches. Objective on 2 threads, paired medians of 15: foam3d at 32,000 faces (level 1)
        # +16 ms (of 86), the 76,800 faces of a 60-bubble reconstruction -1 ms (of 85), foam3d at
        # 128,000 faces (level 2) -9 ms (of 124); at 512,000 faces it saves about 20 % (the
        # item-by-item pass has no supersampling)
        self.by_item = len(f) >= ITEM_MAJOR_FACES and self.k == 1
        # per group, one row per chunk of views: where each item's stored crossings begin in the
        # whole store (raster3d's item-by-item pass)
        self.store_items = {}
        n = frames.n
        self.threads = max(1, min(int(threads), n))
        edges = np.linspace(0, n, self.threads + 1).round().astype(int)
        self.groups = [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]
        # per projection, one bit per face: whether the forward pass found a crossing on it, so
        # the gradient pass visits only those (a projection's row is written by one thread)
        self.hit = np.zeros((n, (len(f) + 7) // 8 if scene.ndim == 3 else 1), np.uint8)
        # Crossings kept by the forward pass for the gradient (face, pixel, 3 coefficients: 32
        # bytes each) while they fit in store_bytes(), shared among the groups by projections;
        # a group that overflows rasterises again in face_sums. Pages are touched only as used.
        npix = n * self.rows * self.cols
        per_projection = store_bytes() // 32 // n if store and scene.ndim == 3 and npix < 2**31 else 0
        self.store = _take_store(per_projection * n) if per_projection else None
        self.stores = {}
        self.store_offset = {}  # where each group's part of the store begins
        for g in self.groups:
            a, b = per_projection * g[0], per_projection * g[1]
            self.store_offset[g] = a
            self.stores[g] = [x[a:b] for x in self.store] + [-1] if self.store else \
                [np.empty(0, np.int32), np.empty(0, np.int32), np.empty((0, 3)), -1]

    def run(self, group, values, weights, acc):
        """Forward (``values`` given) or face sums (``weights``, ``acc`` given) for projections ``group``;
        :class:`DeadlineExceeded` once the deadline has passed (the kernels stop at the flag)."""
        p0, p1 = group
        grad = acc is not None
        dummy1, dummy2 = np.zeros(1), np.zeros((1, 1))
        if not grad and self.scene.ndim == 2:  # raster3d zeroes its views' values itself
            values[p0 * self.cols: p1 * self.cols] = 0.0
        args = (p0, p1, self.vertices, self.faces, self.normals, self.offset, self.face_mu, *self.frames,
                self.cone, self.rows, self.cols, self.k, values if not grad else dummy1,
                weights if grad else dummy1, acc if grad else dummy2, grad)
        if self.scene.ndim == 2:
            count = _state["raster2d"](*args, self.stop)
            check_deadline(self.deadline)
            return count
        face, pix, coef, _ = self.stores[group]
        if grad:  # an empty store: the gradient pass keeps nothing
            face, pix, coef = face[:0], pix[:0], coef[:0]
        starts = np.zeros(len(self.item_faces), np.int64)
        count, stored = _state["raster3d"](*args, self.hit, face, pix, coef, *self.ray_lengths, self.item_vertices,
                                           self.item_faces, self.by_item, starts, self.stop)
        check_deadline(self.deadline)
        if not grad:
            self.stores[group][3] = stored
            self.store_items[group] = [starts + self.store_offset[group]] if stored >= 0 else []
        return count

    def objective(self, group, data):
        """``(f, face sums)`` of projections ``group``, in chunks of views whose crossings fit the group's
        part of the store: each chunk is rasterised (storing), its residual taken in place, and its face
        sums added from the store while the crossings are fresh; a chunk that overflows the store
        rasterises again for its face sums (the faces it marked: on overflow the kernel marks those of
        the crossings it had stored), as :meth:`run` does for a whole group.

        The kernels see a chunk as a scan of its own views (the frames, crossing marks and ray lengths
        of those views; pixel indices from the chunk's first), so its projection needs a buffer of the
        chunk's pixels, not one of the scan's (63 MB of float64 on a 40 x 256 x 768 detector)."""
        from bubsub.core.projection.backends.common_kernels import residual

        p0, p1 = group
        npix = self.rows * self.cols
        k2 = float(self.k * self.k)
        face, pix, coef, _ = self.stores[group]
        room = len(face)
        acc = np.zeros(self.faces.shape)
        dummy1, dummy2 = np.zeros(1), np.zeros((1, 1))
        starts = np.zeros(len(self.item_faces), np.int64)  # raster3d's item starts, not needed here
        scene = (self.vertices, self.faces, self.normals, self.offset, self.face_mu)
        items = (self.item_vertices, self.item_faces)
        rl_all, pix_rl = self.ray_lengths
        buffer = np.empty(0)
        f, p, size, per_view = 0.0, p0, 1, 0.0
        while p < p1:
            check_deadline(self.deadline)
            q = min(p1, p + size)
            span = slice(p * npix, q * npix)
            if buffer.size < (q - p) * npix:
                buffer = np.empty((q - p) * npix)
            values = buffer[:(q - p) * npix]  # zeroed by raster3d
            chunk = (*scene, *(a[p:q] for a in self.frames), self.cone, self.rows, self.cols, self.k)
            hit, rl = self.hit[p:q], rl_all[span] if pix_rl else rl_all
            c, stored = _state["raster3d"](0, q - p, *chunk, values, dummy1, dummy2, False, hit, face, pix, coef,
                                           rl, pix_rl, *items, self.by_item, starts, self.stop)
            # the residual over the sub-rays' weights: face_sums' weights are the residual / k^2
            f += residual(values, k2, data[span], values)
            if k2 > 1:
                values /= k2
            if stored >= 0:
                _state["stored_face_sums"](face, pix, coef, stored, values, acc, rl, pix_rl, self.stop)
            else:
                _state["raster3d"](0, q - p, *chunk, dummy1, values, acc, True, hit, face[:0], pix[:0], coef[:0],
                                   rl, pix_rl, *items, False, starts, self.stop)
                if q - p == 1 and int(1.25 * c) * 32 <= store_bytes():
                    # one view outgrows the group's part of the store: a store of the group's own that holds
                    # one view with a quarter to spare (within the whole budget), or every view is rasterised
                    # twice (dense foams, whose views each hold millions of crossings)
                    room = int(1.25 * c)
                    face, pix, coef = np.empty(room, np.int32), np.empty(room, np.int32), np.empty((room, 3))
            # the next chunk: as many views as the store held of this one's, with a tenth to spare
            per_view = max(per_view, c / (q - p))
            size = max(1, int(0.9 * room / per_view)) if room and per_view > 0 else p1 - q
            p = q
        check_deadline(self.deadline)  # the last chunk's kernels may have stopped at the flag
        return f, acc

    def by_item_store(self):
        """Whether every group kept all its crossings, item by item (raster3d's ``st_item``)."""
        return self.by_item and self.store is not None and all(
            self.stores[g][3] >= 0 for g in self.groups)


def _pixel_ray_lengths(frames, stop, deadline):
    """``(lengths, True)``: every pixel's source-to-detector ray length, computed once per
    :class:`Frames` (a square root per crossing would cost 10 % of an objective); kept only when
    finished (``stop``: the call's stop flag; :class:`DeadlineExceeded` past ``deadline``)."""
    cached = frames.derived.get("raster pixel ray lengths")
    if cached is None:
        S, D, U, V = (np.ascontiguousarray(a, dtype=np.float64) for a in (frames.s, frames.d, frames.u, frames.v))
        cached = np.empty(frames.n * frames.rows * frames.cols)
        _state["pixel_ray_lengths"](S, D, U, V, int(frames.rows), int(frames.cols), cached, stop)
        check_deadline(deadline)
        # two threads may both compute it on a projector's first calls: the same array either way
        frames.derived["raster pixel ray lengths"] = cached
    return cached, True


def _compile():
    from bubsub.core.projection.backends import raster_kernels

    return {"raster3d": raster_kernels.raster3d, "raster2d": raster_kernels.raster2d,
            "stored_face_sums": raster_kernels.stored_face_sums, "item_face_sums": raster_kernels.item_face_sums,
            "pixel_ray_lengths": raster_kernels.pixel_ray_lengths}
