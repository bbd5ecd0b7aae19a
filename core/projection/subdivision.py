"""Subdivision as sparse matrices: Loop surfaces (3D) and cubic B-spline curves (2D).

Subdivision is linear in the control vertices, so ``levels`` rounds of it are
one sparse matrix ``S``: fine vertices = ``S @ control vertices``. The
gradient of anything with respect to the control vertices is then ``S.T @``
the gradient with respect to the fine vertices.
"""

from __future__ import annotations

import threading
import weakref
from functools import lru_cache

import numpy as np
import scipy.sparse as sp

from bubsub.core.projection.mesh import Mesh, Polygon
from bubsub.core.threads import thread_map
from bubsub.core.validate import check_int

__all__ = [
    "loop_subdivision",
    "curve_subdivision",
    "icosphere",
    "SubdivisionSurface",
    "sphere_surface",
    "circle_surface",
    "refine_control",
    "fine_vertices",
    "control_gradients",
]


def _loop_once(faces, n_vertices):
    """One Loop step: (S (n_fine, n) csr, fine faces (4m, 3), edge end points (n_edges, 2))."""
    f = np.asarray(faces, dtype=np.int64)
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    # half-edges (start, end, opposite vertex), one per face corner
    hs = np.concatenate([a, b, c])
    he = np.concatenate([b, c, a])
    ho = np.concatenate([c, a, b])
    key = np.minimum(hs, he) * n_vertices + np.maximum(hs, he)
    uniq, edge_of_half, counts = np.unique(key, return_inverse=True, return_counts=True)
    if np.any(counts != 2):
        raise ValueError("Loop subdivision needs a closed manifold mesh (each edge in two faces)")
    n_edges = counts.size
    edge_row = n_vertices + edge_of_half

    valence = np.bincount(hs, minlength=n_vertices).astype(float)
    if np.any(valence == 0):
        raise ValueError("Loop subdivision needs every vertex to belong to a face")
    beta = (5.0 / 8.0 - (3.0 / 8.0 + 0.25 * np.cos(2.0 * np.pi / valence)) ** 2) / valence

    rows = np.concatenate([np.arange(n_vertices), hs, edge_row, edge_row, edge_row])
    cols = np.concatenate([np.arange(n_vertices), he, hs, he, ho])
    vals = np.concatenate(
        [1.0 - valence * beta, beta[hs], np.full(hs.size, 3 / 16), np.full(hs.size, 3 / 16), np.full(hs.size, 1 / 8)]
    )
    S = sp.csr_matrix((vals, (rows, cols)), shape=(n_vertices + n_edges, n_vertices))

    m = len(f)
    ab, bc, ca = edge_row[:m], edge_row[m: 2 * m], edge_row[2 * m:]
    fine = np.concatenate(
        [np.stack([a, ab, ca], 1), np.stack([b, bc, ab], 1), np.stack([c, ca, bc], 1), np.stack([ab, bc, ca], 1)]
    )
    edges = np.stack([uniq // n_vertices, uniq % n_vertices], axis=1)
    return S, fine, edges


def loop_subdivision(faces, n_vertices, levels):
    """Loop subdivision of a closed triangle mesh as one sparse matrix.

    Parameters
    ----------
    faces : (m, 3) int
        Control mesh triangles.
    n_vertices : int
        Number of control vertices.
    levels : int
        Rounds of subdivision (0 gives the identity).

    Returns
    -------
    S : (n_fine, n_vertices) scipy.sparse.csr_matrix
        ``fine_vertices = S @ control_vertices``; canonical (:func:`_canonical`).
    fine_faces : (m * 4**levels, 3) int
        Fine triangles, oriented as the control faces.
    """
    if levels < 0:
        raise ValueError(f"levels must be >= 0, got {levels}")
    f = np.asarray(faces, dtype=np.int64)
    S = sp.identity(n_vertices, format="csr")
    n = n_vertices
    for _ in range(levels):
        Si, f, _ = _loop_once(f, n)
        S = Si @ S
        n = Si.shape[0]
    return _canonical(S), f


def curve_subdivision(n_vertices, levels):
    """Cubic B-spline subdivision of a closed polygon (the curve analogue of Loop).

    Each step keeps every corner as ``(p[i-1] + 6 p[i] + p[i+1]) / 8`` and
    inserts ``(p[i] + p[i+1]) / 2`` after it, doubling the count and keeping
    the orientation.

    Returns
    -------
    S : (n_vertices * 2**levels, n_vertices) scipy.sparse.csr_matrix
        Canonical (:func:`_canonical`).
    """
    if n_vertices < 3:
        raise ValueError(f"a closed polygon needs at least 3 control points, got {n_vertices}")
    if levels < 0:
        raise ValueError(f"levels must be >= 0, got {levels}")
    S = sp.identity(n_vertices, format="csr")
    n = n_vertices
    for _ in range(levels):
        i = np.arange(n)
        prev, nxt = (i - 1) % n, (i + 1) % n
        rows = np.concatenate([2 * i, 2 * i, 2 * i, 2 * i + 1, 2 * i + 1])
        cols = np.concatenate([prev, i, nxt, i, nxt])
        vals = np.concatenate([np.full(n, 1 / 8), np.full(n, 6 / 8), np.full(n, 1 / 8), np.full(n, 0.5), np.full(n, 0.5)])
        S = sp.csr_matrix((vals, (rows, cols)), shape=(2 * n, n)) @ S
        n *= 2
    return _canonical(S)


def _canonical(S):
    """``S`` as CSR with sorted indices and no duplicates. scipy sorts a matrix's indices in place in
    some operations, which changes the order of its products' sums; a matrix shared by many surfaces
    (:func:`_shared_topology`) would carry that from one fit into the next, so results would depend
    on what ran before."""
    S = S.tocsr()
    S.sum_duplicates()
    return S


@lru_cache(maxsize=8)
def _icosphere(subdivisions):
    # Icosahedron, then midpoint splits projected to the sphere.
    t = (1.0 + 5.0 ** 0.5) / 2.0
    v = np.array(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
         [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
        dtype=float,
    )
    f = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]],
        dtype=np.int64,
    )
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        _, f, edges = _loop_once(f, len(v))
        v = np.vstack([v, 0.5 * (v[edges[:, 0]] + v[edges[:, 1]])])
        v /= np.linalg.norm(v, axis=1, keepdims=True)
    v.setflags(write=False)
    f.setflags(write=False)
    return v, f


def icosphere(subdivisions=1):
    """Unit-sphere control mesh: 12 vertices (``0``), 42 (``1``), 162 (``2``) ...

    Returns
    -------
    vertices : (n, 3) float
    faces : (m, 3) int, outward oriented
    """
    if subdivisions not in range(0, 6):
        raise ValueError(f"subdivisions must be 0..5, got {subdivisions}")
    v, f = _icosphere(int(subdivisions))
    return v.copy(), f.copy()


class _Topology:
    """What every iterate of one subdivision surface shares: S and the fine topology."""

    __slots__ = ("S", "fine_faces", "levels", "__weakref__")

    def __init__(self, control, levels):
        if isinstance(control, Mesh):
            self.S, faces = loop_subdivision(control.faces, len(control.vertices), levels)
            # The fine mesh of a valid control mesh is valid; check it once here.
            self.fine_faces = Mesh(self.S @ control.vertices, faces, control.attenuation).faces
        else:
            self.S = curve_subdivision(len(control.vertices), levels)
            self.fine_faces = None
        self.levels = levels


_TOPOLOGIES_LOCK = threading.Lock()
_TOPOLOGIES = weakref.WeakValueDictionary()  # (kind, levels, n, control faces) -> the _Topology in use


def _shared_topology(control, levels):
    """The :class:`_Topology` of ``control``'s connectivity at ``levels``, shared by every surface built
    with the same one (the bubbles of a foam usually are), so that :func:`fine_vertices` and
    :func:`control_gradients` subdivide them all in one sparse product; kept while a surface uses it."""
    faces = np.asarray(control.faces) if isinstance(control, Mesh) else None
    key = (isinstance(control, Mesh), levels, len(control.vertices),
           None if faces is None else faces.astype(np.int64, copy=False).tobytes())
    with _TOPOLOGIES_LOCK:
        topo = _TOPOLOGIES.get(key)
    if topo is None:
        topo = _Topology(control, levels)
        with _TOPOLOGIES_LOCK:
            topo = _TOPOLOGIES.setdefault(key, topo)
    return topo


def _groups(surfaces):
    """Indices of the subdivision surfaces among ``surfaces``, grouped by shared topology."""
    groups = {}
    for k, s in enumerate(surfaces):
        if isinstance(s, SubdivisionSurface):
            groups.setdefault(id(s._topo), []).append(k)
    return groups.values()


def fine_vertices(items, threads=1):
    """Fine vertices of every item: ``S @ control`` for a :class:`SubdivisionSurface`, ``vertices`` otherwise.

    Surfaces sharing a topology are subdivided in one sparse product (60
    bubbles: 0.3 ms, against 2 ms for one product per surface, at every
    evaluation of a fit). The control vertices of a valid surface are finite,
    and so are these (S has non-negative weights summing to 1).

    Parameters
    ----------
    items : list of SubdivisionSurface, Mesh or Polygon
    threads : int
        Worker threads: a topology's surfaces are split among them once they have
        :data:`THREADED_FINE_VERTICES` fine vertices or more (scipy's product releases the GIL).

    Returns
    -------
    list of (n_k, d) float
        Read-only; views into one array per topology.
    """
    out = [None if isinstance(it, SubdivisionSurface) else it.vertices for it in items]

    def product(ks):
        S = items[ks[0]].S
        control = np.stack([items[k].vertices for k in ks], axis=1)  # (n_control, surfaces, d)
        fine = (S @ control.reshape(len(control), -1)).reshape(S.shape[0], len(ks), -1)
        fine.setflags(write=False)
        for j, k in enumerate(ks):
            out[k] = fine[:, j]

    thread_map(product, _split(items, threads), threads)
    return out


# fine vertices (summed over a topology's surfaces) from which the sparse products through S are
# split among threads: 256,000 took 3.6 ms in one product, and a round trip to the pool 0.1-0.2 ms
THREADED_FINE_VERTICES = 100_000


def _split(items, threads):
    """Each topology's surfaces (:func:`_groups`), in up to ``threads`` parts when it is large
    enough to be worth it."""
    parts = []
    for ks in _groups(items):
        n = min(int(threads), len(ks)) if items[ks[0]].S.shape[0] * len(ks) >= THREADED_FINE_VERTICES else 1
        parts.extend(part.tolist() for part in np.array_split(np.asarray(ks), max(n, 1)))
    return parts


def control_gradients(items, fine_gradients, threads=1):
    """The chain rule through S: ``S.T @ g`` per subdivision surface (one sparse product per topology),
    ``g`` itself for other items.

    Parameters
    ----------
    items : list of SubdivisionSurface, Mesh or Polygon
    fine_gradients : list of (n_fine_k, d) float
    threads : int
        As in :func:`fine_vertices`.

    Returns
    -------
    list of (n_k, d) float
    """
    out = [None if isinstance(it, SubdivisionSurface) else np.asarray(g) for it, g in zip(items, fine_gradients)]

    def product(ks):
        S = items[ks[0]].S
        g = np.stack([fine_gradients[k] for k in ks], axis=1)  # (n_fine, surfaces, d)
        control = (S.T @ g.reshape(len(g), -1)).reshape(S.shape[1], len(ks), -1)
        for j, k in enumerate(ks):
            out[k] = np.ascontiguousarray(control[:, j])

    thread_map(product, _split(items, threads), threads)
    return out


class SubdivisionSurface:
    """A bubble surface: a control Mesh (3D) or Polygon (2D) and its subdivision.

    Parameters
    ----------
    control : Mesh or Polygon
        Control mesh / control polygon; its attenuation is the surface's.
    levels : int
        Subdivision levels (the paper uses 2).

    Notes
    -----
    ``with_vertices`` shares S and the fine topology, so an optimiser can make
    a new surface every iteration at the cost of a sparse product.
    """

    __slots__ = ("control", "_topo")

    def __init__(self, control, levels=2, *, _topology=None):
        if not isinstance(control, (Mesh, Polygon)):
            raise TypeError(f"control must be a Mesh or a Polygon, got {type(control).__name__}")
        check_int(levels, "levels", 0, 6)
        self.control = control
        self._topo = _topology if _topology is not None else _shared_topology(control, int(levels))

    @property
    def ndim(self):
        return 3 if isinstance(self.control, Mesh) else 2

    @property
    def levels(self):
        return self._topo.levels

    @property
    def S(self):
        """(n_fine, n_control) sparse subdivision matrix."""
        return self._topo.S

    @property
    def vertices(self):
        """Control vertices, (n, 3) or (n, 2)."""
        return self.control.vertices

    @property
    def attenuation(self):
        return self.control.attenuation

    @property
    def control_faces(self):
        """Control triangles (3D) or ``None`` (2D)."""
        return np.asarray(self.control.faces) if self.ndim == 3 else None

    def with_vertices(self, vertices):
        return SubdivisionSurface(self.control.with_vertices(vertices), _topology=self._topo)

    def with_attenuation(self, attenuation):
        return SubdivisionSurface(self.control.with_attenuation(attenuation), _topology=self._topo)

    def with_levels(self, levels, *, keep_size=False):
        """The same control mesh subdivided ``levels`` times.

        With ``keep_size`` the control vertices are scaled about their centroid so that the fine mesh
        keeps its mean distance from its centroid: a convex mesh shrinks with each level (a sphere's by
        1.7 % in radius from one level to two at 42 control vertices), and a bubble given the levels of
        its size (:func:`bubsub.clients.pipeline.static.resolution.levels_by_size`) keeps the size it was seeded with.
        """
        if levels == self.levels:
            return self
        new = SubdivisionSurface(self.control, levels)
        if not keep_size:
            return new

        def radius(s):
            fine = s.fine().vertices
            return float(np.linalg.norm(fine - fine.mean(axis=0), axis=1).mean())

        c = self.vertices.mean(axis=0)
        return new.with_vertices(c + (self.vertices - c) * (radius(self) / radius(new)))

    def fine(self):
        """The subdivided Mesh or Polygon."""
        v = self._topo.S @ self.control.vertices
        if self.ndim == 3:
            return Mesh(v, None, self.attenuation, _checked_faces=self._topo.fine_faces)
        return Polygon(v, self.attenuation, _checked=True)

    def __repr__(self):
        return f"SubdivisionSurface({self.control!r}, levels={self.levels})"


def refine_control(surface, levels=None):
    """The same surface with one subdivision step moved into its control mesh (coarse-to-fine fits).

    The new control vertices are one Loop (3D) or cubic B-spline (2D) step of
    the old ones, so the limit surface is unchanged; with ``levels`` one less
    than the surface's (the default) the fine mesh is unchanged too, vertex
    for vertex, and so is its projection's cost. A fit continued from the
    refined surface has about four (3D) or two (2D) times the unknowns, to
    follow details the coarse control mesh cannot (flat films, Plateau
    borders of dense foams).

    Parameters
    ----------
    surface : SubdivisionSurface
    levels : int, optional
        Subdivision levels of the result; default ``max(surface.levels - 1, 0)``.

    Returns
    -------
    SubdivisionSurface
        Control mesh of ``4 m`` triangles (3D, ``m`` the old count) or ``2 n``
        points (2D).
    """
    if not isinstance(surface, SubdivisionSurface):
        raise TypeError(f"refine_control needs a SubdivisionSurface, got {type(surface).__name__}")
    levels = max(surface.levels - 1, 0) if levels is None else levels
    control = surface.control
    n = len(control.vertices)
    if surface.ndim == 3:
        S, faces = loop_subdivision(control.faces, n, 1)
        new = Mesh(S @ control.vertices, faces, control.attenuation)
    else:
        new = Polygon(curve_subdivision(n, 1) @ control.vertices, control.attenuation)
    return SubdivisionSurface(new, levels)


@lru_cache(maxsize=16)
def _limit_scale(kind, n, levels):
    """Factor that makes the subdivided unit sphere/circle have mean radius 1."""
    if kind == 3:
        v, f = _icosphere(n)
        S, _ = loop_subdivision(f, len(v), levels)
        return 1.0 / np.linalg.norm(S @ v, axis=1).mean()
    S = curve_subdivision(n, levels)
    return 1.0 / np.linalg.norm(S @ _unit_circle(n), axis=1).mean()


def _unit_circle(n):
    a = 2 * np.pi * np.arange(n) / n
    return np.stack([np.cos(a), np.sin(a)], axis=1)


_ICO_SIZES = {12: 0, 42: 1, 162: 2}


def sphere_surface(centre, radius, attenuation, control=42, levels=2):
    """A spherical bubble: icosphere control mesh whose subdivision has mean radius ``radius``.

    Parameters
    ----------
    centre : (3,) float
    radius : float, mm
    attenuation : float, 1/mm
    control : {12, 42, 162}
        Number of control vertices.
    levels : int
    """
    if control not in _ICO_SIZES:
        raise ValueError(f"control must be one of {sorted(_ICO_SIZES)}, got {control!r}")
    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius!r}")
    v, f = _icosphere(_ICO_SIZES[control])
    scale = radius * _limit_scale(3, _ICO_SIZES[control], levels)
    c = np.asarray(centre, dtype=float).reshape(3)
    return SubdivisionSurface(Mesh(c + scale * v, f, attenuation), levels)


def circle_surface(centre, radius, attenuation, control=9, levels=2):
    """A circular 2D bubble: ``control`` points whose subdivision has mean radius ``radius``."""
    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius!r}")
    control = int(control)
    c = np.asarray(centre, dtype=float).reshape(2)
    scale = radius * _limit_scale(2, control, levels)
    return SubdivisionSurface(Polygon(c + scale * _unit_circle(control), attenuation), levels)
