"""Scan geometries in ASTRA's vector conventions.

A :class:`ScanGeometry` is immutable. It stores, per projection, the ASTRA
vector row and the detector size, and knows how to turn itself into rays.
One module on purpose: it is one class, whose constructors, ASTRA
conversion, rays, subsets, windows and binning all read the same vector rows.

Kinds and vector rows (ASTRA's definitions):

* ``parallel3d_vec``: ``(rayX, rayY, rayZ, dX, dY, dZ, uX, uY, uZ, vX, vY, vZ)``
* ``cone_vec``: ``(srcX, srcY, srcZ, dX, dY, dZ, uX, uY, uZ, vX, vY, vZ)``
* ``parallel_vec``: ``(rayX, rayY, dX, dY, uX, uY)``
* ``fanflat_vec``: ``(srcX, srcY, dX, dY, uX, uY)``

The centre of detector pixel ``(r, c)`` is
``d + (c - cols/2 + 0.5) u + (r - rows/2 + 0.5) v``.
Projection arrays are ``(angle, row, col)`` in 3D and ``(angle, col)`` in 2D
(the Data Exchange order; ASTRA's own 3D order is ``(row, angle, col)``).
Lengths are in millimetres.
"""

from __future__ import annotations

import numpy as np

from bubsub.core.validate import check_int

__all__ = ["ScanGeometry", "KINDS"]

#: kind -> (dimension, number of values per vector row, is cone/fan)
KINDS = {
    "parallel3d_vec": (3, 12, False),
    "cone_vec": (3, 12, True),
    "parallel_vec": (2, 6, False),
    "fanflat_vec": (2, 6, True),
}


def _positive_int(name, value):
    check_int(value, name, 1)
    return int(value)


def _angles(angles):
    a = np.atleast_1d(np.asarray(angles, dtype=float))
    if a.ndim != 1 or a.size == 0 or not np.all(np.isfinite(a)):
        raise ValueError("angles must be a non-empty 1D array of finite radians")
    return a


def _pixel_size(pixel_size):
    p = np.broadcast_to(np.asarray(pixel_size, dtype=float), (2,))
    if not np.all(np.isfinite(p)) or np.any(p <= 0):
        raise ValueError(f"pixel_size must be positive, got {pixel_size!r}")
    return float(p[0]), float(p[1])


class ScanGeometry:
    """Projection geometry of a scan, one ASTRA vector row per projection.

    Make one with :meth:`parallel`, :meth:`cone` or :meth:`from_astra`.

    Attributes
    ----------
    kind : str
        One of ``parallel3d_vec``, ``cone_vec``, ``parallel_vec``, ``fanflat_vec``.
    vectors : (n_angles, 12) or (n_angles, 6) float, read-only
    det_rows : int or None
        Detector rows (``None`` for 2D kinds).
    det_cols : int
        Detector columns (``det_count`` for 2D kinds).
    """

    __slots__ = ("_kind", "_vectors", "_rows", "_cols", "_repr")

    def __init__(self, kind, vectors, det_rows, det_cols, _repr=None):
        if kind not in KINDS:
            raise ValueError(f"unknown geometry kind {kind!r}; expected one of {sorted(KINDS)}")
        ndim, width, _ = KINDS[kind]
        v = np.array(vectors, dtype=float, copy=True)
        if v.ndim == 1 and v.size == width:
            v = v[None]
        if v.ndim != 2 or v.shape[1] != width or v.shape[0] == 0:
            raise ValueError(
                f"{kind} vectors must have shape (n_angles, {width}), got {np.shape(vectors)}"
            )
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{kind} vectors contain NaN or inf")
        if ndim == 3:
            det_rows = _positive_int("det_rows", det_rows)
        elif det_rows is not None:
            raise ValueError(f"2D kind {kind} takes det_count, not det_rows")
        det_cols = _positive_int("det_cols" if ndim == 3 else "det_count", det_cols)
        u = v[:, 2 * ndim: 3 * ndim]
        if np.any(np.linalg.norm(u, axis=1) == 0):
            raise ValueError("detector u vectors must be non-zero")
        if ndim == 3 and np.any(np.linalg.norm(v[:, 9:12], axis=1) == 0):
            raise ValueError("detector v vectors must be non-zero")
        v.setflags(write=False)
        self._kind, self._vectors, self._rows, self._cols = kind, v, det_rows, det_cols
        self._repr = _repr

    # -- factories --------------------------------------------------------------
    @classmethod
    def parallel(cls, angles, *, pixel_size=1.0, cols, rows=None):
        """Circular parallel-beam scan, as ``astra.geom_2vec`` of ``parallel``/``parallel3d``.

        Parameters
        ----------
        angles : (n,) float
            Projection angles in radians.
        pixel_size : float or (2,) float
            Detector pixel width (and height in 3D), mm.
        cols : int
            Detector columns.
        rows : int, optional
            Detector rows; ``None`` makes a 2D (``parallel_vec``) geometry.
        """
        a = _angles(angles)
        pu, pv = _pixel_size(pixel_size)
        s, c = np.sin(a), np.cos(a)
        z = np.zeros_like(a)
        if rows is None:
            vec = np.stack([s, -c, z, z, c * pu, s * pu], axis=1)
            kind = "parallel_vec"
        else:
            vec = np.stack([s, -c, z, z, z, z, c * pu, s * pu, z, z, z, z + pv], axis=1)
            kind = "parallel3d_vec"
        rep = f"ScanGeometry.parallel({_angles_repr(a)}, pixel_size={pixel_size!r}, cols={cols!r}, rows={rows!r})"
        return cls(kind, vec, rows, cols, _repr=rep)

    @classmethod
    def cone(cls, angles, *, source_origin, origin_detector, pixel_size=1.0, cols, rows=None):
        """Circular cone-beam (or 2D fan-beam) scan, as ``astra.geom_2vec`` of ``cone``/``fanflat``.

        Parameters
        ----------
        angles : (n,) float
            Projection angles in radians.
        source_origin, origin_detector : float
            Distances from the source to the rotation axis and from the axis to
            the detector, mm.
        pixel_size : float or (2,) float
            Detector pixel width (and height in 3D), mm.
        cols : int
        rows : int, optional
            ``None`` makes a 2D (``fanflat_vec``) geometry.
        """
        a = _angles(angles)
        pu, pv = _pixel_size(pixel_size)
        if not (np.isfinite(source_origin) and source_origin > 0):
            raise ValueError(f"source_origin must be positive, got {source_origin!r}")
        if not (np.isfinite(origin_detector) and origin_detector > -source_origin):
            raise ValueError(f"origin_detector must place the detector beyond the source, got {origin_detector!r}")
        s, c = np.sin(a), np.cos(a)
        z = np.zeros_like(a)
        so, od = float(source_origin), float(origin_detector)
        if rows is None:
            vec = np.stack([s * so, -c * so, -s * od, c * od, c * pu, s * pu], axis=1)
            kind = "fanflat_vec"
        else:
            vec = np.stack(
                [s * so, -c * so, z, -s * od, c * od, z, c * pu, s * pu, z, z, z, z + pv], axis=1
            )
            kind = "cone_vec"
        rep = (
            f"ScanGeometry.cone({_angles_repr(a)}, source_origin={source_origin!r}, "
            f"origin_detector={origin_detector!r}, pixel_size={pixel_size!r}, cols={cols!r}, rows={rows!r})"
        )
        return cls(kind, vec, rows, cols, _repr=rep)

    @classmethod
    def from_astra(cls, kind, vectors=None, det_rows=None, det_cols=None, *, det_count=None):
        """Geometry from ASTRA vectors, or from an ASTRA ``proj_geom`` dict.

        ``from_astra("cone_vec", vectors, det_rows, det_cols)``,
        ``from_astra("parallel_vec", vectors, det_count=n)`` or
        ``from_astra(astra.create_proj_geom(...))`` (vector kinds only; convert
        others with ``astra.geom_2vec`` first).
        """
        if isinstance(kind, dict):
            g = kind
            kind = g.get("type")
            if kind not in KINDS:
                raise ValueError(f"ASTRA geometry type {kind!r} is not a vector geometry; use astra.geom_2vec first")
            vectors = g["Vectors"]
            if KINDS[kind][0] == 3:
                det_rows, det_cols = g["DetectorRowCount"], g["DetectorColCount"]
            else:
                det_count = g["DetectorCount"]
        if kind not in KINDS:
            raise ValueError(f"unknown geometry kind {kind!r}; expected one of {sorted(KINDS)}")
        if vectors is None:
            raise ValueError("vectors are required")
        if KINDS[kind][0] == 2:
            if det_rows is not None:
                raise ValueError(f"2D kind {kind} takes det_count, not det_rows")
            if det_count is None:
                det_count = det_cols
            return cls(kind, vectors, None, det_count)
        if det_count is not None:
            raise ValueError(f"3D kind {kind} takes det_rows and det_cols, not det_count")
        return cls(kind, vectors, det_rows, det_cols)

    # -- properties -------------------------------------------------------------
    kind = property(lambda self: self._kind)
    vectors = property(lambda self: self._vectors)
    det_rows = property(lambda self: self._rows)
    det_cols = property(lambda self: self._cols)

    @property
    def det_count(self):
        """Detector pixels per row (2D name of ``det_cols``)."""
        return self._cols

    @property
    def ndim(self):
        """2 or 3."""
        return KINDS[self._kind][0]

    @property
    def is_cone(self):
        """True for cone and fan beams (rays from a point source)."""
        return KINDS[self._kind][2]

    @property
    def n_angles(self):
        return self._vectors.shape[0]

    @property
    def shape(self):
        """Shape of a projection array: ``(angle, row, col)`` or ``(angle, col)``."""
        if self.ndim == 3:
            return (self.n_angles, self._rows, self._cols)
        return (self.n_angles, self._cols)

    def to_astra(self):
        """ASTRA ``proj_geom`` dict (as ``astra.create_proj_geom(kind, ...)`` makes)."""
        g = {"type": self._kind, "Vectors": np.array(self._vectors)}
        if self.ndim == 3:
            g["DetectorRowCount"], g["DetectorColCount"] = self._rows, self._cols
        else:
            g["DetectorCount"] = self._cols
        return g

    def __getitem__(self, index):
        """Geometry of a subset of projections (``g[::2]``, ``g[[0, 3]]``, ``g[5]``)."""
        idx = np.arange(self.n_angles)[index]
        idx = np.atleast_1d(idx)
        if idx.size == 0:
            raise IndexError("a geometry needs at least one projection")
        return ScanGeometry(self._kind, self._vectors[idx], self._rows, self._cols)

    def __len__(self):
        return self.n_angles

    def window(self, row_start, col_start, rows=None, cols=None):
        """The same scan seen through a smaller detector: ``rows x cols`` pixels starting at
        ``(row_start[p], col_start[p])`` in projection ``p`` (scalars apply to all projections).

        Projecting onto the window gives ``full[p, r0:r0 + rows, c0:c0 + cols]`` of projecting onto
        the whole detector (:meth:`window_of` cuts an array so).

        Parameters
        ----------
        row_start, col_start : int or (n_angles,) int
            First pixel of the window (2D geometries: ``row_start`` must be 0).
        rows, cols : int
            Window size (``rows`` None in 2D).

        Raises
        ------
        ValueError
            If a window does not lie on the detector.
        """
        n = self.n_angles
        r0 = np.broadcast_to(np.asarray(row_start), (n,)).astype(np.int64)
        c0 = np.broadcast_to(np.asarray(col_start), (n,)).astype(np.int64)
        cols = _positive_int("cols", cols)
        if self.ndim == 3:
            rows = _positive_int("rows", rows)
            if np.any(r0 < 0) or np.any(r0 + rows > self._rows):
                raise ValueError(f"window rows [{r0.min()}, {r0.max() + rows}) leave the detector's {self._rows} rows")
        elif np.any(r0 != 0) or rows is not None:
            raise ValueError("a 2D detector has one row: row_start must be 0 and rows None")
        if np.any(c0 < 0) or np.any(c0 + cols > self._cols):
            raise ValueError(f"window columns [{c0.min()}, {c0.max() + cols}) leave the detector's {self._cols} columns")
        nd = self.ndim
        v = np.array(self._vectors)
        # the detector centre moves to the window's centre, along u (columns) and v (rows)
        shift = (c0 + 0.5 * cols - 0.5 * self._cols)[:, None] * v[:, 2 * nd:3 * nd]
        if nd == 3:
            shift += (r0 + 0.5 * rows - 0.5 * self._rows)[:, None] * v[:, 9:12]
        v[:, nd:2 * nd] += shift
        return ScanGeometry(self._kind, v, rows, cols,
                            _repr=f"{self!r}.window(<{n} row starts>, <{n} column starts>, rows={rows}, cols={cols})")

    def binned(self, factor):
        """The detector with ``factor x factor`` pixels joined into one (``factor`` columns in 2D).

        Rows and columns that do not fill a whole binned pixel (the last
        ``cols % factor``) are dropped; the detector's centre moves so that
        binned pixel ``(r, c)`` covers pixels ``factor r ... factor r + factor - 1``
        (and columns alike) of this one. :meth:`bin_projections` bins an array so.

        Parameters
        ----------
        factor : int
            At least 1, at most the detector's columns (and rows).
        """
        f = _positive_int("factor", factor)
        nd = self.ndim
        if f > self._cols or (nd == 3 and f > self._rows):
            raise ValueError(f"cannot bin a {self.shape[1:]} detector by {f}")
        if f == 1:
            return self
        v = np.array(self._vectors)
        u = v[:, 2 * nd:3 * nd].copy()
        cols = self._cols // f
        v[:, nd:2 * nd] += 0.5 * (f * cols - self._cols) * u
        v[:, 2 * nd:3 * nd] = f * u
        rows = None
        if nd == 3:
            w = v[:, 9:12].copy()
            rows = self._rows // f
            v[:, nd:2 * nd] += 0.5 * (f * rows - self._rows) * w
            v[:, 9:12] = f * w
        return ScanGeometry(self._kind, v, rows, cols, _repr=f"{self!r}.binned({f})")

    @staticmethod
    def bin_projections(projections, factor):
        """Projections binned as :meth:`binned`: the mean of each ``factor x factor`` block (float32)."""
        a = np.asarray(projections, dtype=np.float32)
        f = int(factor)
        if f == 1:
            return a
        if a.ndim == 2:
            n, c = a.shape
            return a[:, :c // f * f].reshape(n, c // f, f).mean(axis=2)
        n, r, c = a.shape
        return a[:, :r // f * f, :c // f * f].reshape(n, r // f, f, c // f, f).mean(axis=(2, 4))

    def translated(self, origin):
        """The same scan in world coordinates whose origin is ``origin`` of these.

        A point ``x`` of this geometry's world is ``x - origin`` in the new
        one; the rays, and so every projection, are the same. (A slab of
        detector rows is reconstructed about its own centre this way.)

        Parameters
        ----------
        origin : (ndim,) float
            mm.
        """
        nd = self.ndim
        o = np.asarray(origin, dtype=float).reshape(-1)
        if o.shape != (nd,) or not np.all(np.isfinite(o)):
            raise ValueError(f"origin must be {nd} finite coordinates, got {origin!r}")
        return self._shifted(o, f"{self!r}.translated({o.tolist()!r})")

    def _shifted(self, offset, text):
        """The rays of each view moved by ``-offset`` (``(ndim,)`` or ``(n_angles, ndim)`` mm), repr ``text``."""
        nd = self.ndim
        v = np.array(self._vectors)
        v[:, nd:2 * nd] -= offset  # detector positions; a parallel ray direction does not move
        if self.is_cone:
            v[:, :nd] -= offset  # the source does
        return ScanGeometry(self._kind, v, self._rows, self._cols, _repr=text)

    def moved(self, displacements):
        """The scan of a sample that moves between projections, seen from the sample: its position at projection
        ``k`` is ``displacements[k]`` from where this geometry's world has it, and the result projects the
        sample standing still there (each view's rays translated by ``-displacements[k]``, :meth:`translated`).

        Parameters
        ----------
        displacements : (n_angles, ndim) float
            mm.
        """
        nd = self.ndim
        d = np.asarray(displacements, dtype=float)
        if d.shape != (self.n_angles, nd) or not np.all(np.isfinite(d)):
            raise ValueError(f"displacements must be ({self.n_angles}, {nd}) finite mm, got shape {d.shape}")
        return self._shifted(d, f"{self!r}.moved(<{self.n_angles} x {nd} displacements>)")

    @staticmethod
    def window_of(projections, row_start, col_start, rows=None, cols=None):
        """``projections[p, r0[p]:r0[p] + rows, c0[p]:c0[p] + cols]`` for every p (see :meth:`window`)."""
        a = np.asarray(projections)
        n = a.shape[0]
        c0 = np.broadcast_to(np.asarray(col_start), (n,)).astype(np.int64)
        cidx = c0[:, None] + np.arange(cols)[None]
        if a.ndim == 2:
            return a[np.arange(n)[:, None], cidx]
        r0 = np.broadcast_to(np.asarray(row_start), (n,)).astype(np.int64)
        ridx = r0[:, None] + np.arange(rows)[None]
        return a[np.arange(n)[:, None, None], ridx[:, :, None], cidx[:, None, :]]

    def detector_coordinates(self, points):
        """Where the ray through each point meets the detector, in pixels from its centre.

        Parameters
        ----------
        points : (m, ndim) float
            mm.

        Returns
        -------
        col, row : (n_angles, m) float
            Along u and v, in pixels, 0 at the detector centre (``row`` zeros in 2D); the pixel
            index is ``col + det_cols / 2 - 0.5``.
        ahead : (n_angles, m) bool
            False where the point is not in front of a cone source (its coordinates mean nothing).
        """
        n = self.ndim
        p = np.asarray(points, dtype=float).reshape(-1, n)
        vec = self._vectors
        s, d, u = vec[:, :n], vec[:, n:2 * n], vec[:, 2 * n:3 * n]
        if n == 3:
            v = vec[:, 9:12]
            normal = np.cross(u, v)
        else:
            v = None
            normal = np.stack([-u[:, 1], u[:, 0]], axis=1)
        # where the ray through each point meets the detector plane: (angles, points, ndim)
        if self.is_cone:
            ray = p[None] - s[:, None]
            t = np.einsum("ak,ak->a", d - s, normal)[:, None] / np.einsum("apk,ak->ap", ray, normal)
            hit = s[:, None] + t[..., None] * ray
            ahead = t > 0
        else:
            t = np.einsum("apk,ak->ap", d[:, None] - p[None], normal) / np.einsum("ak,ak->a", s, normal)[:, None]
            hit = p[None] + t[..., None] * s[:, None]
            ahead = np.ones(t.shape, bool)
        rel = hit - d[:, None]
        if v is None:
            col = np.einsum("apk,ak->ap", rel, u) / np.einsum("ak,ak->a", u, u)[:, None]
            return col, np.zeros_like(col), ahead
        # dual basis of (u, v) in the detector plane: exact for skewed detectors too
        vn, nu = np.cross(v, normal), np.cross(normal, u)
        col = np.einsum("apk,ak->ap", rel, vn) / np.einsum("ak,ak->a", u, vn)[:, None]
        row = np.einsum("apk,ak->ap", rel, nu) / np.einsum("ak,ak->a", v, nu)[:, None]
        return col, row, ahead


    def __eq__(self, other):
        return (
            isinstance(other, ScanGeometry)
            and self._kind == other._kind
            and self._rows == other._rows
            and self._cols == other._cols
            and np.array_equal(self._vectors, other._vectors)
        )

    def __hash__(self):
        return hash((self._kind, self._rows, self._cols, self._vectors.tobytes()))

    def __repr__(self):
        if self._repr is not None:
            return self._repr
        if self.ndim == 3:
            size = f"det_rows={self._rows}, det_cols={self._cols}"
        else:
            size = f"det_count={self._cols}"
        return f"ScanGeometry.from_astra({self._kind!r}, <{self.n_angles} x {self._vectors.shape[1]} vectors>, {size})"

    # -- rays -------------------------------------------------------------------
    def pixel_centres(self):
        """World coordinates of every detector pixel centre.

        Returns
        -------
        (*shape, 3) float
            2D geometries are embedded in the plane z = 0.
        """
        return self._detector_points(np.zeros(1), np.zeros(1))[..., 0, :]

    def _detector_points(self, du, dv):
        """Points on each pixel at sub-pixel offsets ``(du[k], dv[k])`` (fractions of a pixel).

        Returns (*shape, k, 3) float.
        """
        vec = self._vectors
        n = self.n_angles
        if self.ndim == 3:
            d, u, v = vec[:, 3:6], vec[:, 6:9], vec[:, 9:12]
            r = np.arange(self._rows) - self._rows / 2 + 0.5
            c = np.arange(self._cols) - self._cols / 2 + 0.5
            cu = c[None, None, :, None] + du[None, None, None, :]  # (1,1,cols,k)
            rv = r[None, :, None, None] + dv[None, None, None, :]  # (1,rows,1,k)
            pts = (
                d[:, None, None, None, :]
                + cu[..., None] * u[:, None, None, None, :]
                + rv[..., None] * v[:, None, None, None, :]
            )
            return pts
        d = np.concatenate([vec[:, 2:4], np.zeros((n, 1))], axis=1)
        u = np.concatenate([vec[:, 4:6], np.zeros((n, 1))], axis=1)
        c = np.arange(self._cols) - self._cols / 2 + 0.5
        cu = c[None, :, None] + du[None, None, :]
        return d[:, None, None, :] + cu[..., None] * u[:, None, None, :]

    def rays(self, supersampling=1):
        """Ray origins and unit directions, ``supersampling**2`` rays per pixel.

        Sub-rays sit at the centres of a regular ``k x k`` grid over the pixel
        (in 2D, ``k`` rays along the pixel width).

        Returns
        -------
        origins : (*shape, k2, 3) float
            A point on each ray: the source for cone/fan beams, the pixel
            point for parallel beams.
        directions : (*shape, k2, 3) float
            Unit ray directions, pointing from the source towards the detector.
        """
        k = _positive_int("supersampling", supersampling)
        off = (np.arange(k) + 0.5) / k - 0.5
        if self.ndim == 3:
            du, dv = np.repeat(off, k), np.tile(off, k)
        else:
            du, dv = off, np.zeros(k)
        pts = self._detector_points(du, dv)
        vec = self._vectors
        ndim = self.ndim
        src = vec[:, :ndim]
        if ndim == 2:
            src = np.concatenate([src, np.zeros((self.n_angles, 1))], axis=1)
        src = src.reshape((self.n_angles,) + (1,) * (pts.ndim - 2) + (3,))
        if self.is_cone:
            directions = pts - src
            origins = np.broadcast_to(src, pts.shape)
        else:
            directions = np.broadcast_to(src, pts.shape)
            origins = pts
        directions = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
        return origins, directions


def _angles_repr(a):
    if a.size > 1:
        step = a[1] - a[0]
        if np.allclose(np.diff(a), step, rtol=0, atol=1e-12 * max(1.0, abs(step))):
            return f"np.linspace({float(a[0])!r}, {float(a[-1])!r}, {a.size})"
    return f"{a.tolist()!r}"
