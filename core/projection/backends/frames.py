"""Per-projection scan frames, and the ray-major driver shared by the Embree backends (ray set-up, culling, chunks, threads)."""

from __future__ import annotations

import numpy as np

from bubsub.core.projection.backends.base import Backend, StoredCrossings, check_deadline, deadline_map, stop_flag

__all__ = ["Frames", "RayCaster", "EPS_REL"]

EPS_REL = 1e-5  # restart offset after a hit, relative to the scene size
RAY_CHUNK = 1 << 17  #: rays per work item


def _item_spheres(scene):
    """Per item: bounding-sphere centre (shifted; z = 0 in 2D, where rays run) and radius."""
    counts = np.diff(scene.vertex_offset)
    starts = scene.vertex_offset[:-1]
    lo = np.minimum.reduceat(scene.vertices, starts, axis=0)
    hi = np.maximum.reduceat(scene.vertices, starts, axis=0)
    centre = 0.5 * (lo + hi)
    nd = scene.ndim
    if nd == 2:
        centre[:, 2] = 0.0
    dist2 = np.sum((scene.vertices[:, :nd] - np.repeat(centre, counts, axis=0)[:, :nd]) ** 2, axis=1)
    return centre, np.sqrt(np.maximum.reduceat(dist2, starts))


class Frames:
    """Per-projection source/ray, detector origin and axes, as (n, 3) arrays.

    2D geometries become 3D ones with a single detector row along z.

    Attributes
    ----------
    s, d, u, v : (n, 3) float
        Source (cone) or ray direction (parallel), detector centre, and the
        detector's column and row steps, per projection (ASTRA's vectors).
    rows, cols : int
    cone : bool
    ndim, n : int
    derived : dict
        Arrays a backend derives from the frames once and reuses at every
        call (a projector keeps one Frames), keyed by the backend's name for
        them; e.g. the raster backend's per-pixel ray lengths.
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
        self.derived = {}

    def __getstate__(self):
        # derived arrays are rebuilt where they are used: a projector sent to a worker
        # should not carry, say, 26 MB of ray lengths with it
        state = self.__dict__.copy()
        state["derived"] = {}
        return state

    def check_scene(self, scene):
        """Refuse what no backend projects meaningfully.

        Cone/fan beams: a vertex behind the source (or in the plane through
        it parallel to the detector) has no central projection. Parallel
        beams: rays parallel to the detector plane never reach it.
        """
        nrm = np.cross(self.u, self.v)
        if not self.cone:
            bad = np.flatnonzero(np.einsum("ij,ij->i", self.s, nrm) == 0)
            if bad.size:
                raise ValueError(f"projection {bad[0]}: the rays run parallel to the detector plane")
            return
        src_all = self.s - scene.centre
        h_all = np.einsum("ij,ij->i", self.d - self.s, nrm)
        # the scene's bounding sphere (about the origin of the shifted frame) wholly in front
        # of a source settles that projection without visiting the vertices
        radius = float(np.linalg.norm(scene.half)) * (1 + 1e-9)
        clear = -np.einsum("ij,ij->i", src_all, nrm) * np.sign(h_all) > radius * np.linalg.norm(nrm, axis=1)
        for p in np.flatnonzero(~clear):
            src = src_all[p]
            h = h_all[p]
            if h == 0:
                raise ValueError(f"projection {p}: the cone source lies in the detector plane")
            depth = (scene.vertices - src) @ nrm[p]
            behind = np.flatnonzero(depth * np.sign(h) <= 0)
            if behind.size:
                i = int(behind[0])
                item = int(np.searchsorted(scene.vertex_offset, i, side="right") - 1)
                x = scene.vertices[i] + scene.centre
                raise ValueError(
                    f"item {item} has a vertex at ({x[0]:.4g}, {x[1]:.4g}, {x[2]:.4g}) mm behind (or level with) "
                    f"the cone source of projection {p} at ({self.s[p][0]:.4g}, {self.s[p][1]:.4g}, {self.s[p][2]:.4g}) mm; "
                    f"every vertex must lie between the source's plane and the detector side")

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

    def candidate_pixels(self, scene, deadline=None):
        """Pixels whose rays may hit some item's bounding sphere, and how far they need to go.

        Each sphere is enclosed in a cube aligned with the detector, whose
        projected corners bound the pixels it can shadow. For each such pixel
        the farthest side of the spheres over it bounds where its last
        crossing can be, so rays stop there instead of casting a last, long
        miss through the scene. View by view, ``deadline`` (a
        :func:`time.monotonic` value) checked before each.

        Returns
        -------
        pixel : (k,) int64
            Sorted flat pixel indices.
        far : (k,) float
            Cone/fan: distance from the source past which no crossing lies.
            Parallel: the same as depth along the ray, from the scene centre.
        """
        centre, radius = _item_spheres(scene)
        m = len(centre)
        signs = np.array([[(i >> j) & 1 for j in range(3)] for i in range(8)], float) * 2 - 1
        npix = self.rows * self.cols
        pixels, fars = [], []
        shift = scene.centre
        for p in range(self.n):
            check_deadline(deadline)
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
                    pixels.append(np.arange(p * npix, (p + 1) * npix))  # a sphere around or behind the source:
                    fars.append(np.full(npix, np.inf))  # cast everything
                    continue
                P = s + lam[:, None] * (X - s)
            else:
                ray = self.s[p]
                item_far = centre @ (ray / np.linalg.norm(ray)) + radius
                den = ray @ nrm
                if den == 0:
                    pixels.append(np.arange(p * npix, (p + 1) * npix))
                    fars.append(np.full(npix, np.inf))
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
            fp = np.full((self.rows, self.cols), -np.inf)
            for k in range(m):
                view = fp[r0[k]:r1[k], c0[k]:c1[k]]
                np.maximum(view, item_far[k], out=view)
            fp = fp.ravel()
            pixel = np.flatnonzero(fp > -np.inf)
            pixels.append(pixel + p * npix)
            fars.append(fp[pixel])
        # joined view by view, the deadline checked before each: writing hundreds of MB into fresh pages
        # is itself a fair share of a second
        total = sum(len(a) for a in pixels)
        pixel, far = np.empty(total, np.int64), np.empty(total)
        pos = 0
        for a, f in zip(pixels, fars):
            check_deadline(deadline)
            pixel[pos:pos + len(a)], far[pos:pos + len(a)] = a, f
            pos += len(a)
        return pixel, far


class RayCaster(Backend):
    """Ray-major casting shared by the Embree backends: candidate pixels, chunks of rays, threads.

    Subclasses build their Embree scene in :meth:`prepare` and trace one
    chunk of rays in :meth:`trace_chunk`.
    """

    prisms_2d = True

    def trace(self, scene, frames, sub, threads, gradient=False, deadline=None):
        size = float(np.max(scene.half[:scene.ndim])) * 2.0
        eps = EPS_REL * max(size, 1e-3)
        caster = self.prepare(scene, eps)
        pix, far = frames.candidate_pixels(scene, deadline)
        far += 4 * eps
        # every ray starts just before the scene's bounding sphere
        radius = float(np.linalg.norm(scene.half)) + 4 * eps
        n_rays = pix.size * sub.shape[0]
        halt = stop_flag(deadline)  # the casters read it every few thousand rays

        def chunk(s):  # rays go in pixel order, so a chunk of rays is a chunk of views
            check_deadline(deadline)
            out = caster.trace_chunk(frames, sub, pix, far, radius, s, min(s + RAY_CHUNK, n_rays), halt)
            check_deadline(deadline)  # the chunk may have stopped at the flag
            return out

        chunks = deadline_map(chunk, range(0, n_rays, RAY_CHUNK), threads)
        values = np.zeros(frames.n * frames.rows * frames.cols)
        for lo, part, _ in chunks:
            values[lo: lo + part.size] += part
        return StoredCrossings(values, [c for _, _, c in chunks], scene,
                               lambda fn, items: deadline_map(fn, items, threads), deadline)

    def prepare(self, scene, eps):
        """An object with ``trace_chunk(frames, sub, pix, far, radius, start, stop, halt)`` for this scene
        (``halt``: the stop flag, :func:`~bubsub.core.projection.backends.base.stop_flag`)."""
        raise NotImplementedError
