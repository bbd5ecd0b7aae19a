"""Closed triangle meshes (3D bubbles) and closed polygons (2D bubbles).

Both are validated once, on construction: finite coordinates, indices in
range, closed, consistently and outwardly oriented. ``with_vertices`` makes a
copy with moved vertices that keeps the checked topology (only finiteness and
shape are checked again), which is what an optimiser calls every iteration.
"""

from __future__ import annotations

import numpy as np

__all__ = ["Mesh", "Polygon", "bounding_box", "equivalent_radius", "volume_in_slab"]


def equivalent_radius(size, ndim):
    """Radius (mm) of the ball (``ndim`` 3) or disc (2) of the given volume or area; 0 for a size <= 0.

    Parameters
    ----------
    size : float or ndarray
        Volume (mm^3) or area (mm^2).
    ndim : {2, 3}

    Returns
    -------
    float or ndarray, like ``size``
    """
    size = np.maximum(size, 0.0)
    r = np.cbrt(3.0 * size / (4.0 * np.pi)) if ndim == 3 else np.sqrt(size / np.pi)
    return float(r) if np.ndim(r) == 0 else r


def _volume_below(tri, height):
    """Volume of the part below ``z = height`` of the solid bounded by outward triangles ``tri`` (m, 3, 3).

    Gauss's theorem with the field ``(0, 0, z - height)``, which vanishes on
    the cutting plane: the volume is the sum over the surface's part below
    the plane of ``(z - height) n_z dA``, and the plane's cap adds nothing,
    so the triangles are clipped and the cap is never built. Exact for the
    triangle mesh.
    """
    below = tri[..., 2] < height
    n = below.sum(axis=1)
    pieces = [tri[n == 3]]
    for case in (1, 2):
        t, b = tri[n == case], below[n == case]
        # the vertex alone on its side first, the cyclic order (and so the orientation) kept
        first = np.argmax(b if case == 1 else ~b, axis=1)
        t = np.take_along_axis(t, ((first[:, None] + np.arange(3)) % 3)[:, :, None], axis=1)
        a, p, q = t[:, 0], t[:, 1], t[:, 2]
        ap = a + (p - a) * ((height - a[:, 2]) / (p[:, 2] - a[:, 2]))[:, None]
        aq = a + (q - a) * ((height - a[:, 2]) / (q[:, 2] - a[:, 2]))[:, None]
        if case == 1:  # a below: the triangle (a, ap, aq)
            pieces.append(np.stack([a, ap, aq], axis=1))
        else:  # a above: the quadrilateral (ap, p, q, aq) as two triangles
            pieces += [np.stack([ap, p, q], axis=1), np.stack([ap, q, aq], axis=1)]
    t = np.concatenate(pieces)
    nz = 0.5 * ((t[:, 1, 0] - t[:, 0, 0]) * (t[:, 2, 1] - t[:, 0, 1])
                - (t[:, 1, 1] - t[:, 0, 1]) * (t[:, 2, 0] - t[:, 0, 0]))
    return float(np.sum(nz * (t[:, :, 2].mean(axis=1) - height)))


def volume_in_slab(vertices, faces, z_min, z_max):
    """Volume of a closed, outwardly oriented triangle mesh's part between two horizontal planes.

    Exact for the mesh (the triangles are clipped by each plane; no grid),
    for the part of a bubble that a detector's rows see.

    Parameters
    ----------
    vertices : (n, 3) float
    faces : (m, 3) int
    z_min, z_max : float
        The planes, ``z_min <= z_max``.

    Returns
    -------
    float
        mm^3 (the mesh's units cubed).
    """
    if z_min > z_max:
        raise ValueError(f"volume_in_slab: z_min {z_min} lies above z_max {z_max}")
    tri = np.asarray(vertices, dtype=float)[np.asarray(faces)]
    return max(_volume_below(tri, z_max) - _volume_below(tri, z_min), 0.0)


def bounding_box(points):
    """Per-coordinate minimum and maximum of ``points`` ((n, d) float): two (d,) arrays.

    Column by column: numpy's ``min(axis=0)`` over a tall (n, 3) array is
    about twenty times slower (10 ms for the 256,000 vertices of a finely
    subdivided scene, on every objective evaluation).
    """
    points = np.asarray(points)
    lo = np.array([points[:, j].min() for j in range(points.shape[1])])
    hi = np.array([points[:, j].max() for j in range(points.shape[1])])
    return lo, hi


def _attenuation(value):
    try:
        mu = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"attenuation must be a number, got {value!r}") from None
    if not np.isfinite(mu):
        raise ValueError(f"attenuation must be finite, got {value!r}")
    return mu


def _vertices(vertices, dim, name="vertices"):
    try:
        v = np.array(vertices, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a numeric (n, {dim}) array") from None
    if v.ndim != 2 or v.shape[1] != dim:
        raise ValueError(f"{name} must have shape (n, {dim}), got {v.shape}")
    if not np.all(np.isfinite(v)):
        bad = int(np.count_nonzero(~np.isfinite(v).all(axis=1)))
        raise ValueError(f"{name} contain NaN or inf ({bad} of {len(v)} vertices)")
    v.setflags(write=False)
    return v


class Mesh:
    """A closed, outward-oriented triangle mesh with a constant attenuation.

    Parameters
    ----------
    vertices : (n, 3) float
        Vertex coordinates, mm.
    faces : (m, 3) int
        Vertex indices of each triangle, counter-clockwise seen from outside.
    attenuation : float
        Attenuation inside the mesh, 1/mm (negative for a gas bubble inside
        a liquid container mesh).

    Raises
    ------
    ValueError
        If coordinates are not finite, indices are out of range, a face is
        degenerate, the surface is open or not consistently oriented, or it
        encloses a negative volume (inward orientation).
    """

    __slots__ = ("vertices", "faces", "attenuation")

    def __init__(self, vertices, faces, attenuation=1.0, *, _checked_faces=None):
        self.vertices = _vertices(vertices, 3)
        self.attenuation = _attenuation(attenuation)
        if _checked_faces is not None:
            if len(self.vertices) != _checked_faces.n_vertices:
                raise ValueError(
                    f"vertices must have shape ({_checked_faces.n_vertices}, 3), got {self.vertices.shape}"
                )
            self.faces = _checked_faces
            return
        f = _faces(faces, len(self.vertices))
        _check_closed_oriented(f)
        self.faces = _Faces(f, len(self.vertices))
        if self.volume <= 0:
            raise ValueError("mesh is oriented inwards (negative enclosed volume); reverse the face order")

    def with_vertices(self, vertices):
        """The same topology and attenuation with new vertices ``(n, 3)``."""
        return Mesh(vertices, None, self.attenuation, _checked_faces=self.faces)

    def with_attenuation(self, attenuation):
        return Mesh(self.vertices, None, attenuation, _checked_faces=self.faces)

    @property
    def volume(self):
        """Enclosed volume, mm^3 (divergence theorem)."""
        a, b, c = (self.vertices[self.faces[:, i]] for i in range(3))
        return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)

    @property
    def size(self):
        """The bubble's size: its enclosed volume, mm^3 (:attr:`area` for a :class:`Polygon`)."""
        return self.volume

    @property
    def equivalent_radius(self):
        """Radius of the ball of the same volume, mm (0 for a mesh turned inside out)."""
        return equivalent_radius(self.volume, 3)

    @property
    def area(self):
        """Surface area, mm^2."""
        a, b, c = (self.vertices[self.faces[:, i]] for i in range(3))
        return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())

    @property
    def mean_edge(self):
        """Mean length of the triangles' edges, mm (each edge of a closed mesh counted once per side)."""
        v, f = self.vertices, self.faces
        return float(np.linalg.norm(v[f] - v[np.roll(f, -1, axis=1)], axis=2).mean())

    @property
    def centroid(self):
        """Centroid of the enclosed solid, (3,) mm."""
        a, b, c = (self.vertices[self.faces[:, i]] for i in range(3))
        vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
        return (vol[:, None] * (a + b + c) / 4.0).sum(axis=0) / vol.sum()

    def __repr__(self):
        return f"Mesh(<{len(self.vertices)} vertices>, <{len(self.faces)} faces>, attenuation={self.attenuation!r})"


class _Faces(np.ndarray):
    """A read-only face array that remembers it was validated for n vertices."""

    def __new__(cls, faces, n_vertices):
        obj = np.asarray(faces, dtype=np.int64).view(cls)
        obj.n_vertices = n_vertices
        obj.setflags(write=False)
        return obj

    def __array_finalize__(self, obj):
        self.n_vertices = getattr(obj, "n_vertices", None)

    def __reduce__(self):
        # ndarray's own reduce drops Python attributes: without this a mesh
        # shipped to a worker process forgets how many vertices its faces fit.
        return _Faces, (np.asarray(self), self.n_vertices)


def _faces(faces, n_vertices):
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"faces must have shape (m, 3), got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        if not np.issubdtype(f.dtype, np.floating) or not np.all(np.mod(f, 1) == 0):
            raise ValueError("faces must hold integer vertex indices")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= n_vertices:
        raise ValueError(f"faces index vertices out of range [0, {n_vertices}): min {f.min()}, max {f.max()}")
    if np.any((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])):
        raise ValueError("faces contain a degenerate triangle (a repeated vertex index)")
    return f


def _check_closed_oriented(f):
    """Every directed edge once, and its reverse exactly once."""
    n = int(f.max()) + 1
    src = f.ravel()
    dst = f[:, [1, 2, 0]].ravel()
    key = src * n + dst
    uniq, counts = np.unique(key, return_counts=True)
    if np.any(counts > 1):
        raise ValueError("mesh is not consistently oriented (a directed edge is used by two faces)")
    rev = dst * n + src
    if not np.all(np.isin(rev, uniq)):
        raise ValueError("mesh is not closed (an edge belongs to only one face)")


class Polygon:
    """A closed, counter-clockwise polygon with a constant attenuation (2D bubble).

    Parameters
    ----------
    vertices : (n, 2) float
        Corner coordinates (x, y), mm, counter-clockwise; the last corner
        connects back to the first (do not repeat the first one).
    attenuation : float
        Attenuation inside, 1/mm.
    """

    __slots__ = ("vertices", "attenuation")

    def __init__(self, vertices, attenuation=1.0, *, _checked=False):
        self.vertices = _vertices(vertices, 2)
        self.attenuation = _attenuation(attenuation)
        if _checked:
            return
        if len(self.vertices) < 3:
            raise ValueError(f"a polygon needs at least 3 vertices, got {len(self.vertices)}")
        if self.area <= 0:
            raise ValueError("polygon is clockwise or degenerate (non-positive signed area); give it counter-clockwise")

    def with_vertices(self, vertices):
        """The same attenuation with new vertices ``(n, 2)`` (count must match)."""
        v = _vertices(vertices, 2)
        if v.shape != self.vertices.shape:
            raise ValueError(f"vertices must have shape {self.vertices.shape}, got {v.shape}")
        return Polygon(v, self.attenuation, _checked=True)

    def with_attenuation(self, attenuation):
        return Polygon(self.vertices, attenuation, _checked=True)

    @property
    def faces(self):
        """Edges as vertex index pairs, (n, 2) int."""
        n = len(self.vertices)
        i = np.arange(n)
        return np.stack([i, (i + 1) % n], axis=1)

    @property
    def area(self):
        """Signed area (positive for counter-clockwise), mm^2."""
        x, y = self.vertices.T
        return float(0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))

    @property
    def size(self):
        """The bubble's size: its signed area, mm^2 (:attr:`Mesh.volume` for a mesh)."""
        return self.area

    @property
    def equivalent_radius(self):
        """Radius of the disc of the same area, mm (0 for a clockwise polygon)."""
        return equivalent_radius(self.area, 2)

    @property
    def perimeter(self):
        """Length of the boundary, mm."""
        return float(np.linalg.norm(np.roll(self.vertices, -1, axis=0) - self.vertices, axis=1).sum())

    @property
    def mean_edge(self):
        """Mean length of the boundary's segments, mm."""
        return self.perimeter / len(self.vertices)

    @property
    def centroid(self):
        """(2,) mm."""
        x, y = self.vertices.T
        x1, y1 = np.roll(x, -1), np.roll(y, -1)
        cross = x * y1 - x1 * y
        a = cross.sum() / 2.0
        return np.array([((x + x1) * cross).sum(), ((y + y1) * cross).sum()]) / (6.0 * a)

    def __repr__(self):
        return f"Polygon(<{len(self.vertices)} vertices>, attenuation={self.attenuation!r})"
