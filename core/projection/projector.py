"""Exact X-ray projection of closed triangle meshes with Embree, and its gradient.

Each detector pixel's value is the sum over meshes of ``attenuation x (length
of the ray inside the mesh)``. Rays are cast with Embree, through one of two
backends that find the same crossings: ``native`` (:mod:`.embree_native`: one
traversal per ray whose filter records every hit) or ``embreex`` (closest-hit
casts, re-cast from just past the previous hit, bookkeeping in numpy).

Why the crossings are exact and counted once
-------------------------------------------
* The scene is shifted so its bounding box is centred on the origin and every
  ray starts just before that box. Float32 then resolves positions relative to
  the scene's size, whatever the source distance (300 mm or 50 m) or the
  scene's offset from the world origin.
* (embreex backend) After a hit the ray restarts ``eps = 1e-5 x scene size`` past it. That is far
  above float32 round-off, so a ray cannot hit the same triangle twice; a ray
  through a shared edge can still report both triangles.
* Crossings are then paired per ray and per mesh: a closed, outward mesh is
  entered (n.d < 0) and left (n.d > 0) alternately. An enter counts only when
  the next crossing of that mesh is an exit, and vice versa. Doubled crossings
  (edges, vertices) and a tangent pair closer than ``eps`` (one of which may be
  skipped) then contribute at most ``eps`` instead of a whole chord.

Gradient: moving vertex ``i`` of a crossed triangle by ``dv`` changes the
crossing distance by ``b_i n.dv / (n.d)``; entering crossings count negative,
so the chord's derivative is ``b_i n / |n.d|`` for both (``b_i`` barycentric
weight, ``n`` unit normal, ``d`` unit ray direction).

2D scans use the same engine: each polygon is extruded into a prism along z and
rays are cast in the plane z = 0.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.projection.mesh import Mesh, Polygon
from bubsub.core.projection.subdivision import SubdivisionSurface
from bubsub.core.projection.backends import embree_native

__all__ = ["MeshProjector", "Traversal"]

_EPS_REL = 1e-5  # restart offset after a hit, relative to the scene size
_CHUNK = 1 << 17  # rays per work item


def _embree():
    try:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except ImportError as exc:  # pragma: no cover - embreex is a hard dependency
        raise ImportError("the mesh projector needs embreex (pip install embreex)") from exc
    return rtcore_scene, TriangleMesh


class Traversal:
    """The valid ray-surface crossings of one traversal, shared by value and gradient.

    Kept in the work chunks that found them, so value and gradient are
    reduced chunk by chunk on the worker threads.

    Attributes
    ----------
    values : (n_pixels,) float
        Projection (not yet averaged over sub-rays), flat.
    chunks : list of tuple
        Per chunk: ``pixel (k,) int64``, ``face (k,) int32``,
        ``bary (k, 3) float32``, ``inv_cos (k,) float32`` (``1 / |n.d|``).
    """

    def __init__(self, values, chunks):
        self.values = values
        self.chunks = chunks

    @property
    def count(self):
        """Number of valid crossings."""
        return sum(c[0].size for c in self.chunks)


class _Scene:
    """A triangle soup of all items, shifted to be centred on the origin."""

    def __init__(self, items, ndim, backend="embreex"):
        self.items = list(items)
        resolved = []
        for k, item in enumerate(self.items):
            fine = item.fine() if isinstance(item, SubdivisionSurface) else item
            expected = Mesh if ndim == 3 else Polygon
            if not isinstance(fine, expected):
                raise TypeError(
                    f"item {k} is a {type(item).__name__} of {type(fine).__name__}; "
                    f"a {ndim}D geometry projects {expected.__name__} or SubdivisionSurface of {expected.__name__}"
                )
            resolved.append(fine)
        if not resolved:
            raise ValueError("nothing to project: give at least one mesh")
        self.fine = resolved
        if ndim == 3:
            verts = [m.vertices for m in resolved]
            faces = [np.asarray(m.faces) for m in resolved]
        else:
            # Short walls (about one edge long) keep the triangles well shaped
            # for Embree's BVH; rays run at z = 0, so any height is exact.
            edges = np.concatenate([np.linalg.norm(np.diff(p.vertices, axis=0, append=p.vertices[:1]), axis=1) for p in resolved])
            self.half_height = max(float(np.median(edges)), 1e-6)
            verts, faces = zip(*(_prism(p.vertices, self.half_height) for p in resolved))
        counts = np.array([len(v) for v in verts])
        self.vertex_offset = np.concatenate([[0], np.cumsum(counts)])
        nface = np.array([len(f) for f in faces])
        self.face_item = np.repeat(np.arange(len(resolved)), nface)
        vertices = np.concatenate(verts)
        self.faces = np.concatenate([f + o for f, o in zip(faces, self.vertex_offset[:-1])])
        self.mu = np.array([m.attenuation for m in resolved])
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        self.centre = 0.5 * (lo + hi)
        self.vertices = vertices - self.centre
        self.half = 0.5 * (hi - lo)
        if ndim == 2:
            self.half[2] = self.half_height
        size = float(np.max(self.half[:ndim])) * 2.0
        self.eps = _EPS_REL * max(size, 1e-3)
        a, b, c = (self.vertices[self.faces[:, i]] for i in range(3))
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n, axis=1)
        n[norm > 0] /= norm[norm > 0, None]
        self.normals = n
        # per-item bounding boxes (shifted), for culling pixels per projection
        # per-item bounding spheres (shifted), for culling pixels per projection
        starts = self.vertex_offset[:-1]
        lo_i = np.minimum.reduceat(self.vertices, starts, axis=0)
        hi_i = np.maximum.reduceat(self.vertices, starts, axis=0)
        self.item_centre = 0.5 * (lo_i + hi_i)
        if ndim == 2:
            self.item_centre[:, 2] = 0.0  # rays run in the plane z = 0
        dist2 = np.sum((self.vertices[:, :ndim] - np.repeat(self.item_centre, counts, axis=0)[:, :ndim]) ** 2, axis=1)
        self.item_radius = np.sqrt(np.maximum.reduceat(dist2, starts))
        if backend == "native":
            self.native = embree_native.NativeScene(self.vertices, self.faces)
            return
        self.normals32 = n.astype(np.float32)  # the embreex path's cosines are float32 like its rays
        rtcs, TriangleMesh = _embree()
        self.embree = rtcs.EmbreeScene(robust=True)
        TriangleMesh(self.embree, self.vertices.astype(np.float32), self.faces.astype(np.int32))
        # commit now: concurrent first queries would each try to commit
        one = np.zeros((1, 3), np.float32)
        self.embree.run(one, one + np.float32(1), output=1)

    def item_gradients(self, vertex_grad):
        """Split per-vertex gradients into one array per item (chain S and the prism)."""
        out = []
        for k, item in enumerate(self.items):
            g = vertex_grad[self.vertex_offset[k]: self.vertex_offset[k + 1]]
            if isinstance(self.fine[k], Polygon):
                n = len(self.fine[k].vertices)
                g = g[:n, :2] + g[n:, :2]
            if isinstance(item, SubdivisionSurface):
                g = item.S.T @ g
            out.append(np.asarray(g))
        return out


def _prism(poly, h):
    """Side walls of the polygon extruded to z in [-h, h], outward oriented."""
    n = len(poly)
    v = np.concatenate([np.c_[poly, np.full(n, -h)], np.c_[poly, np.full(n, h)]])
    i = np.arange(n)
    j = (i + 1) % n
    faces = np.concatenate([np.stack([i, j, j + n], 1), np.stack([i, j + n, i + n], 1)])
    return v, faces


class MeshProjector:
    """Ray-casting projector of closed meshes for one scan geometry.

    Parameters
    ----------
    geometry : ScanGeometry
    supersampling : int
        ``k``: cast ``k x k`` rays per pixel (``k`` in 2D) and average them,
        modelling the finite pixel width.
    threads : int, optional
        Worker threads for ray casting (Embree releases the GIL); defaults
        to the number of usable cores.
    backend : {"auto", "native", "embreex"}
        How rays are cast; both give the same crossings. ``"native"`` calls
        Embree 4 directly from compiled (numba) code and collects all of a
        ray's crossings in one traversal; ``"embreex"`` casts through
        embreex's closest-hit interface, once per crossing, in numpy.
        ``"auto"`` takes the environment variable ``BUBSUB_BACKEND`` when
        set, else ``"native"`` where it is available
        (:func:`bubsub.core.projection.backends.embree_native.available`).

    Notes
    -----
    Items to project are :class:`Mesh` (3D), :class:`Polygon` (2D) or
    :class:`SubdivisionSurface`; gradients are with respect to each item's own
    vertices (the control vertices of a subdivision surface). Projections are
    float32 of shape ``geometry.shape``; lengths in mm, attenuation in 1/mm.
    """

    def __init__(self, geometry, supersampling=1, threads=None, backend="auto"):
        source = "backend"
        if backend == "auto" and os.environ.get("BUBSUB_BACKEND", "auto") != "auto":
            backend, source = os.environ["BUBSUB_BACKEND"], "BUBSUB_BACKEND"
        if backend not in ("auto", "native", "embreex"):
            raise ValueError(f"{source} must be 'auto', 'native' or 'embreex', got {backend!r}")
        if backend == "native" and not embree_native.available():
            raise RuntimeError(f"the native backend is unavailable: {embree_native.unavailable_reason()}")
        if backend == "auto":
            backend = "native" if embree_native.available() else "embreex"
        self.backend = backend
        if not isinstance(geometry, ScanGeometry):
            raise TypeError(f"geometry must be a ScanGeometry, got {type(geometry).__name__}")
        if isinstance(supersampling, bool) or not isinstance(supersampling, (int, np.integer)) or not 1 <= supersampling <= 16:
            raise ValueError(f"supersampling must be an integer in 1..16, got {supersampling!r}")
        self.geometry = geometry
        self.supersampling = int(supersampling)
        if threads is None:
            threads = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        self.threads = max(1, int(threads))
        self._frames = _Frames(geometry)
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
    def forward(self, meshes):
        """Projections of ``meshes``: float32 array of ``geometry.shape``."""
        scene = self._scene(meshes)
        return self._projection(self.trace(scene))

    def vjp(self, meshes, residual):
        """Gradient of ``<forward(meshes), residual>`` with respect to each item's vertices.

        Parameters
        ----------
        meshes : sequence of Mesh, Polygon or SubdivisionSurface
        residual : array of ``geometry.shape``

        Returns
        -------
        list of (n_i, 3) or (n_i, 2) float
        """
        r = self._check_array(residual, "residual")
        scene = self._scene(meshes)
        return scene.item_gradients(self._vertex_vjp(scene, self.trace(scene), r))

    def objective(self, meshes, data):
        """``f = 0.5 ||forward(meshes) - data||^2`` and its gradient, from one traversal.

        Returns
        -------
        f : float
        grads : list of (n_i, 3) or (n_i, 2) float
        """
        d = self._check_array(data, "data")
        scene = self._scene(meshes)
        traversal = self.trace(scene)
        # the float32 projection is what forward() returns; f and the gradient use it too
        residual = self._projection(traversal).astype(np.float64) - d
        f = 0.5 * float(np.dot(residual.ravel(), residual.ravel()))
        return f, scene.item_gradients(self._vertex_vjp(scene, traversal, residual))

    def trace(self, meshes):
        """Cast all rays once: a :class:`Traversal` holding every valid crossing."""
        scene = meshes if isinstance(meshes, _Scene) else self._scene(meshes)
        pix, far = self._frames.candidate_pixels(scene)
        far += 4 * scene.eps
        k2 = self._sub.shape[0]
        n_rays = pix.size * k2
        chunks = self._map(lambda s: self._trace_chunk(scene, pix, far, s, min(s + _CHUNK, n_rays)), range(0, n_rays, _CHUNK))
        values = np.zeros(int(np.prod(self.range_shape)))
        for lo, part, crossings in chunks:
            values[lo: lo + part.size] += part
        return Traversal(values, [c for _, _, c in chunks])

    # -- internals ----------------------------------------------------------------
    def _map(self, fn, items):
        items = list(items)
        if self.threads > 1 and len(items) > 1:
            with ThreadPoolExecutor(self.threads) as ex:
                return list(ex.map(fn, items))
        return [fn(i) for i in items]

    def _scene(self, meshes):
        if isinstance(meshes, (Mesh, Polygon, SubdivisionSurface)):
            meshes = [meshes]
        return _Scene(meshes, self.geometry.ndim, self.backend)

    def _check_array(self, a, name):
        if not isinstance(a, np.ndarray):
            a = np.asarray(a)
        if a.shape != self.range_shape:
            raise ValueError(f"{name} must have shape {self.range_shape} (geometry.shape), got {a.shape}")
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise ValueError(f"{name} must be a real float array, got dtype {a.dtype}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contains NaN or inf")
        return a.astype(np.float64, copy=False)

    def _projection(self, traversal):
        k2 = self._sub.shape[0]
        out = traversal.values / k2 if k2 > 1 else traversal.values
        return out.reshape(self.range_shape).astype(np.float32)

    def _vertex_vjp(self, scene, traversal, residual):
        k2 = self._sub.shape[0]
        r = residual.ravel() / k2 if k2 > 1 else residual.ravel()
        mu = scene.mu[scene.face_item]
        nf = len(scene.faces)

        def per_face(chunk):
            # n is constant on a face, so sum b_j * coef per face first
            pixel, face, bary, inv_cos = chunk
            coef = r[pixel] * inv_cos * mu[face]
            return np.stack([np.bincount(face, weights=coef * bary[:, j], minlength=nf) for j in range(3)], axis=1)

        acc = sum(self._map(per_face, traversal.chunks), np.zeros((nf, 3)))
        nv = len(scene.vertices)
        out = np.zeros((nv, 3))
        for c in range(3):
            w = acc * scene.normals[:, c:c + 1]  # (nf, 3 corners)
            out[:, c] = np.bincount(scene.faces.ravel(), weights=w.ravel(), minlength=nv)
        return out

    def _trace_chunk(self, scene, pix, far, start, stop):
        """Trace rays ``start:stop``; returns (first pixel, values from it, crossings)."""
        # every ray starts just before the scene's bounding sphere
        radius = float(np.linalg.norm(scene.half)) + 4 * scene.eps
        if self.backend == "native":
            f = self._frames
            return embree_native.trace_rays(scene.native, pix, far, start, stop, self._sub,
                                            (f.s, f.d, f.u, f.v, f.cone, f.rows, f.cols), scene.centre, radius,
                                            scene.face_item, scene.mu, scene.normals)
        k2 = self._sub.shape[0]
        ray = np.arange(start, stop)
        which = slice(start, stop) if k2 == 1 else ray // k2
        pixel = pix[which]
        od, length = self._frames.rays(pixel, self._sub[ray % k2], scene.centre, radius, far[which])
        idx = np.arange(len(od))  # ray of each still active row
        toff = np.zeros(len(od))
        hit_ray, hit_prim, hit_t, hit_u, hit_v, hit_cos = [], [], [], [], [], []
        eps = scene.eps
        normals = scene.normals32
        while idx.size:
            res = scene.embree.run(od[:, :3], od[:, 3:], dists=(length - toff).astype(np.float32), output=1)
            h = np.flatnonzero(res["primID"] >= 0)
            prim = res["primID"][h]
            t = res["tfar"][h].astype(np.float64)
            idx, od, length = idx[h], od[h], length[h]
            toff = toff[h] + t
            hit_ray.append(idx)
            hit_prim.append(prim)
            hit_t.append(toff)
            hit_u.append(res["u"][h])
            hit_v.append(res["v"][h])
            hit_cos.append(np.einsum("ij,ij->i", normals[prim], od[:, 3:]))
            toff = toff + eps  # restart just past the hit
            od[:, :3] += ((t + eps)[:, None] * od[:, 3:]).astype(np.float32)
            more = toff < length
            if not more.all():
                idx, toff, od, length = idx[more], toff[more], od[more], length[more]
        lo = int(pixel[0]) if pixel.size else 0
        if not hit_ray:
            e = np.empty(0)
            return lo, e, (e.astype(np.int64), e.astype(np.int32), np.empty((0, 3), np.float32), e.astype(np.float32))
        r = np.concatenate(hit_ray)
        face = np.concatenate(hit_prim)
        t = np.concatenate(hit_t)
        u = np.concatenate(hit_u)
        v = np.concatenate(hit_v)
        cos = np.concatenate(hit_cos)
        exiting = cos > 0
        item = scene.face_item[face]
        # Stable sort by (ray, item): hits of one ray were recorded in t order.
        order = np.argsort(r * len(scene.fine) + item, kind="stable")
        r, face, t, u, v, cos, exiting, item = (a[order] for a in (r, face, t, u, v, cos, exiting, item))
        same_next = np.zeros(r.size, bool)
        same_next[:-1] = (r[1:] == r[:-1]) & (item[1:] == item[:-1])
        ok = ~exiting & same_next  # an entry followed by an exit of the same mesh
        ok[:-1] &= exiting[1:]
        ok[1:] |= ok[:-1]  # ... and that exit
        r, face, t, u, v, cos, exiting = (a[ok] for a in (r, face, t, u, v, cos, exiting))
        px = pixel[r]
        part = np.bincount(px - lo, weights=scene.mu[scene.face_item[face]] * np.where(exiting, t, -t))
        with np.errstate(divide="ignore"):
            inv_cos = (1.0 / np.abs(cos)).astype(np.float32)
        bary = np.stack([1.0 - u - v, u, v], axis=1).astype(np.float32)
        return lo, part, (px, face.astype(np.int32), bary, inv_cos)


class _Frames:
    """Per-projection source/ray, detector origin and axes, as (n, 3) arrays.

    2D geometries become 3D ones with a single detector row along z.
    """

    def __init__(self, g):
        vec = g.vectors
        n = g.n_angles
        self.cone = g.is_cone
        if g.ndim == 3:
            self.s, self.d, self.u, self.v = vec[:, 0:3], vec[:, 3:6], vec[:, 6:9], vec[:, 9:12]
            self.rows, self.cols = g.det_rows, g.det_cols
        else:
            z = np.zeros((n, 1))
            self.s, self.d, self.u = (np.concatenate([vec[:, i:i + 2], z], 1) for i in (0, 2, 4))
            self.v = np.tile([0.0, 0.0, 1.0], (n, 1))
            self.rows, self.cols = 1, g.det_count
        self.ndim = g.ndim
        self.n = n

    def rays(self, pixel, sub, shift, radius, far):
        """Sub-rays of sorted flat pixels, starting on a sphere around ``shift``.

        Returns
        -------
        od : (n, 6) float32
            The point where each ray enters the sphere of ``radius`` about
            ``shift`` (relative to ``shift``), and the unit direction; computed
            in float64 per projection, so a far source loses no precision.
        length : (n,) float
            Distance from that point to ``far`` (see :meth:`candidate_pixels`),
            at most ``2 radius``.
        """
        npix = self.rows * self.cols
        p = pixel // npix
        r, c = np.divmod(pixel - p * npix, self.cols)
        a = c + (0.5 - self.cols / 2) + sub[:, 0]
        b = r + (0.5 - self.rows / 2) + sub[:, 1] if self.ndim == 3 else np.zeros(len(pixel))
        od = np.empty((len(pixel), 6), np.float32)
        length = np.empty(len(pixel))
        cuts = np.concatenate([[0], np.flatnonzero(np.diff(p)) + 1, [len(p)]])
        for i0, i1 in zip(cuts[:-1], cuts[1:]):
            q = p[i0]
            aa, bb = a[i0:i1, None], b[i0:i1, None]
            if self.cone:
                src = self.s[q] - shift
                dirs = (self.d[q] - self.s[q]) + aa * self.u[q] + bb * self.v[q]
                dirs /= np.sqrt(np.einsum("ij,ij->i", dirs, dirs))[:, None]
                base = src
            else:
                ray = self.s[q] / np.linalg.norm(self.s[q])
                base = (self.d[q] - shift) + aa * self.u[q] + bb * self.v[q]
                dirs = np.broadcast_to(ray, base.shape)
            tc = -(base @ ray) if not self.cone else -(dirs @ src)
            od[i0:i1, :3] = base + (tc - radius)[:, None] * dirs
            od[i0:i1, 3:] = dirs
            # cone: far is a distance from the source; parallel: a depth from the centre
            length[i0:i1] = far[i0:i1] - (tc - radius) if self.cone else far[i0:i1] + radius
        np.minimum(length, 2 * radius, out=length)
        return od, length

    def candidate_pixels(self, scene):
        """Pixels whose rays may hit some item's bounding sphere, and how far they need to go.

        Each sphere is enclosed in a cube aligned with the detector, whose
        projected corners bound the pixels it can shadow. For each such pixel
        the farthest side of the spheres over it bounds where its last
        crossing can be, so rays stop there instead of casting a last, long
        miss through the scene.

        Returns
        -------
        pixel : (k,) int64
            Sorted flat pixel indices.
        far : (k,) float
            Cone/fan: distance from the source past which no crossing lies.
            Parallel: the same as depth along the ray, from the scene centre.
        """
        m = len(scene.item_centre)
        signs = np.array([[(i >> j) & 1 for j in range(3)] for i in range(8)], float) * 2 - 1
        far = np.full((self.n, self.rows, self.cols), -np.inf)
        shift = scene.centre
        centre, radius = scene.item_centre, scene.item_radius
        for p in range(self.n):
            d, u, v = self.d[p] - shift, self.u[p], self.v[p]
            nrm = np.cross(u, v)
            axes = np.stack([u / np.linalg.norm(u), v / np.linalg.norm(v), nrm / np.linalg.norm(nrm)])
            X = (centre[:, None, :] + radius[:, None, None] * (signs @ axes)).reshape(-1, 3)
            if self.cone:
                s = self.s[p] - shift
                item_far = np.linalg.norm(centre - s, axis=1) + radius
                den = (X - s) @ nrm
                lam = ((d - s) @ nrm) / np.where(den == 0, np.nan, den)
                if not np.all(np.isfinite(lam) & (lam > 0)):
                    far[p] = np.inf  # a sphere around or behind the source: cast everything
                    continue
                P = s + lam[:, None] * (X - s)
            else:
                ray = self.s[p]
                item_far = centre @ (ray / np.linalg.norm(ray)) + radius
                den = ray @ nrm
                if den == 0:
                    far[p] = np.inf
                    continue
                P = X + (((d - X) @ nrm) / den)[:, None] * ray
            rel = P - d
            a = rel @ np.cross(v, nrm) / (u @ np.cross(v, nrm))
            b = rel @ np.cross(nrm, u) / (v @ np.cross(nrm, u))
            col = (a + self.cols / 2 - 0.5).reshape(m, 8)
            row = (b + self.rows / 2 - 0.5).reshape(m, 8)
            c0 = np.clip(np.floor(col.min(1)) - 1, 0, self.cols).astype(int)
            c1 = np.clip(np.ceil(col.max(1)) + 2, 0, self.cols).astype(int)
            r0 = np.clip(np.floor(row.min(1)) - 1, 0, self.rows).astype(int)
            r1 = np.clip(np.ceil(row.max(1)) + 2, 0, self.rows).astype(int)
            if self.ndim == 2:
                r0[:], r1[:] = 0, 1
            fp = far[p]
            for k in range(m):
                view = fp[r0[k]:r1[k], c0[k]:c1[k]]
                np.maximum(view, item_far[k], out=view)
        far = far.ravel()
        pixel = np.flatnonzero(far > -np.inf)
        return pixel, far[pixel]
