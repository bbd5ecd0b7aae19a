"""Geometric validity of bubbles: self-intersecting outlines and interpenetrating bubbles.

A bubble's projection is only meaningful when its surface is simple (a
self-intersecting outline counts part of its gas with the wrong sign and its
shoelace area is wrong) and when no two bubbles share gas (the projector
would count the overlap twice). These checks find both, for 2D polygons and
3D triangle meshes, and for the control as well as the subdivided (fine)
surfaces of :class:`~bubsub.core.projection.subdivision.SubdivisionSurface`.

* 2D crossings: exact segment-segment intersection tests (numpy, all pairs of
  edges; outlines have tens to a few hundred edges).
* 3D crossings: each edge is cast as a ray against the triangles with
  trimesh's Embree ray interface (a BVH); two closed triangle meshes, or one
  mesh with itself, intersect exactly when an edge of one crosses a triangle
  of the other that it does not share a vertex with.
* Overlap area / volume: pixel centres of a small grid over the two bounding
  boxes' intersection tested inside both with :func:`bubsub.core.projection.masks.coverage`
  (winding numbers), so also a bubble wholly inside another is found.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from bubsub.core.projection.mesh import Mesh, Polygon, bounding_box
from bubsub.core.projection.masks import coverage

__all__ = ["Violation", "segment_crossings", "self_crossings", "self_crossing_vertices",
           "crossings_between", "overlap_measure",
           "check_bubbles"]

#: grid points per axis over a pair's bounding-box intersection when measuring an overlap
OVERLAP_SAMPLES = {2: 64, 3: 24}


@dataclass(frozen=True)
class Violation:
    """One validity problem.

    Attributes
    ----------
    kind : {"self_intersection", "inverted", "overlap"}
        ``inverted``: a simple surface enclosing a non-positive signed area
        (volume), i.e. turned inside out.
    bubbles : tuple of int
        The bubble (one index) or the pair (two indices), into the checked list.
    surface : {"control", "fine"}
        Which surface of the bubble(s) (``"fine"`` for plain polygons/meshes).
    crossings : int
        Crossing edge pairs (2D) or edge-triangle crossings (3D).
    measure : float
        For overlaps, the sampled shared area (mm^2) or volume (mm^3); for
        inverted bubbles the signed area (volume); else 0.
    """

    kind: str
    bubbles: tuple
    surface: str
    crossings: int
    measure: float = 0.0

    def as_dict(self):
        return {"kind": self.kind, "bubbles": [int(b) for b in self.bubbles], "surface": self.surface,
                "crossings": int(self.crossings), "measure": float(self.measure)}


# -- 2D -----------------------------------------------------------------------------------
def _cross(o, a, b):
    return (a[..., 0] - o[..., 0]) * (b[..., 1] - o[..., 1]) - (a[..., 1] - o[..., 1]) * (b[..., 0] - o[..., 0])


def segment_crossings(p0, p1, q0, q1):
    """Which segments ``p0-p1`` cross which segments ``q0-q1`` (proper crossings and touching).

    Parameters
    ----------
    p0, p1 : (n, 2) float
    q0, q1 : (m, 2) float

    Returns
    -------
    (n, m) bool
        True where the two closed segments share a point (collinear overlaps
        included).
    """
    P0, P1 = p0[:, None, :], p1[:, None, :]
    Q0, Q1 = q0[None, :, :], q1[None, :, :]
    d1, d2 = _cross(Q0, Q1, P0), _cross(Q0, Q1, P1)
    d3, d4 = _cross(P0, P1, Q0), _cross(P0, P1, Q1)
    proper = (d1 * d2 < 0) & (d3 * d4 < 0)

    def on(a, b, c, d):  # c collinear with a-b and within its box
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        return (d == 0) & np.all((c >= lo) & (c <= hi), axis=-1)

    touch = on(Q0, Q1, P0, d1) | on(Q0, Q1, P1, d2) | on(P0, P1, Q0, d3) | on(P0, P1, Q1, d4)
    return proper | touch


def _polygon_self_hits(v):
    """``(i, j)``: the pairs of edges (edge k from vertex k to k + 1) that cross, ``i < j``."""
    n = len(v)
    a, b = v, np.roll(v, -1, axis=0)
    hit = segment_crossings(a, b, a, b)
    i, j = np.triu_indices(n, k=2)
    # neighbouring edges share a vertex by construction; the first and last edge too
    keep = ~((i == 0) & (j == n - 1))
    i, j = i[keep], j[keep]
    pick = hit[i, j]
    return i[pick], j[pick]


def _polygon_self_crossings(v):
    return len(_polygon_self_hits(v)[0])


# -- 3D -----------------------------------------------------------------------------------
def _trimesh(vertices, faces):
    import trimesh

    return trimesh.Trimesh(np.asarray(vertices, dtype=float), np.asarray(faces), process=False)


def _edges(faces):
    """The mesh's edges (k, 2), each as (lower, higher) vertex, in lexicographic order."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1).astype(np.int64)
    # one integer per edge: np.unique over rows (axis=0) sorts a structured view, 10x slower
    n = int(e.max()) + 1 if len(e) else 1
    key = np.unique(e[:, 0] * n + e[:, 1])
    return np.stack([key // n, key % n], axis=1)


def _edge_hits(target, origins, ends, exclude_shared=None):
    """Edge-triangle crossings: segments ``origins -> ends`` cast against ``target``.

    Returns the (segment index, triangle index) pairs where a segment crosses
    a triangle strictly between its end points; with ``exclude_shared =
    (edges, faces)`` pairs whose triangle has one of the edge's vertices are
    ignored (a mesh tested against itself).
    """
    d = ends - origins
    length = np.linalg.norm(d, axis=1)
    ok = length > 0
    if not ok.any():
        return np.zeros((0, 2), dtype=int)
    idx = np.nonzero(ok)[0]
    unit = d[ok] / length[ok, None]
    tri, ray, loc = target.ray.intersects_id(origins[ok], unit, multiple_hits=True, return_locations=True)
    if len(tri) == 0:
        return np.zeros((0, 2), dtype=int)
    t = np.einsum("ij,ij->i", loc - origins[ok][ray], unit[ray])
    eps = 1e-9 * float(np.ptp(target.vertices, axis=0).max() or 1.0)
    inside = (t > eps) & (t < length[ok][ray] - eps)
    seg, tri = idx[ray[inside]], tri[inside]
    if exclude_shared is not None:
        edges, faces = exclude_shared
        f = faces[tri]
        shared = np.any(f == edges[seg, 0:1], axis=1) | np.any(f == edges[seg, 1:2], axis=1)
        seg, tri = seg[~shared], tri[~shared]
    return np.unique(np.stack([seg, tri], axis=1), axis=0)


def _mesh_self_hits(vertices, faces):
    """``(edges, faces, hits)``: the mesh's edges and its (edge, triangle) self-crossings."""
    faces = np.asarray(faces)
    edges = _edges(faces)
    tm = _RayMesh.__new__(_RayMesh)  # its scene freed on return (no Trimesh.ray reference cycle)
    tm.vertices = np.asarray(vertices, dtype=float)
    tm.ray = _intersector(tm.vertices, faces)
    return edges, faces, _edge_hits(tm, vertices[edges[:, 0]], vertices[edges[:, 1]], exclude_shared=(edges, faces))


def _intersector(vertices, faces):
    """trimesh's embreex ray intersector of the mesh, its scene on the one shared Embree device."""
    return _shared_device_intersector()(_trimesh(vertices, faces))


_SHARED = {}


def _shared_device_intersector():
    """The class of :func:`_intersector` (made once: it needs trimesh and embreex, imported on first use).

    trimesh's intersector gives every scene an Embree device of its own, and
    Embree fails (a null pointer, the process killed by SIGSEGV) once about a
    thousand devices are alive at once: a repair's check of a foam of 2400
    bubbles holds a scene per bubble. Scenes on one shared device have no
    such bound (5000 alive were tested).
    """
    if "class" not in _SHARED:
        from embreex import rtcore, rtcore_scene
        from embreex.mesh_construction import TriangleMesh
        from trimesh.ray import ray_pyembree

        device = rtcore.EmbreeDevice()

        class SharedScene:
            """The scene and query scaling of trimesh's wrapper (float32 coordinates of the mesh moved to
            its box's corner and scaled to about 100), on ``device``."""

            def __init__(self, vertices, faces, scale):
                v = np.asarray(vertices, dtype=np.float64)
                self.origin, self.scale = v.min(axis=0), float(scale)
                self.scene = rtcore_scene.EmbreeScene(device)
                TriangleMesh(scene=self.scene, vertices=((v - self.origin) * self.scale).astype(np.float32),
                             indices=np.asarray(faces).astype(np.int32))

            def run(self, origins, directions, **kwargs):
                o = (np.asarray(origins, dtype=np.float64) - self.origin) * self.scale
                return self.scene.run(o.astype(np.float32), np.asarray(directions).astype(np.float32), **kwargs)

        class Intersector(ray_pyembree.RayMeshIntersector):
            @property
            def _scene(self):
                if "scene" not in self.__dict__:
                    self.__dict__["scene"] = SharedScene(self.mesh.vertices, self.mesh.faces, self._scale)
                return self.__dict__["scene"]

        _SHARED["class"] = Intersector
    return _SHARED["class"]


def _mesh_self_crossings(vertices, faces):
    return len(_mesh_self_hits(vertices, faces)[2])


# -- public checks --------------------------------------------------------------------------
def _surfaces_of(item):
    """``[("control", Polygon|Mesh), ("fine", ...)]`` of a subdivision surface, ``[("fine", item)]`` otherwise."""
    if isinstance(item, (Mesh, Polygon)):
        return [("fine", item)]
    if hasattr(item, "fine") and hasattr(item, "control"):
        return [("control", item.control), ("fine", item.fine())]
    raise TypeError(f"expected a Polygon, Mesh or SubdivisionSurface, got {type(item).__name__}")


def self_crossings(item):
    """Number of crossings of a polygon (edge pairs) or triangle mesh (edge-triangle pairs) with itself.

    Parameters
    ----------
    item : Polygon or Mesh

    Returns
    -------
    int
        0 for a simple outline / an embedded surface.
    """
    if isinstance(item, Polygon):
        return _polygon_self_crossings(item.vertices)
    if isinstance(item, Mesh):
        return _mesh_self_crossings(item.vertices, item.faces)
    raise TypeError(f"expected a Polygon or Mesh, got {type(item).__name__}")


def self_crossing_vertices(item):
    """Vertices of the edges (and triangles) that take part in a self-crossing, sorted indices.

    Parameters
    ----------
    item : Polygon or Mesh

    Returns
    -------
    (k,) int
        Empty for a simple outline / an embedded surface; else the end points
        of each crossing edge and, in 3D, the corners of each crossed triangle.
    """
    if isinstance(item, Polygon):
        n = len(item.vertices)
        i, j = _polygon_self_hits(item.vertices)
        return np.unique(np.concatenate([i, (i + 1) % n, j, (j + 1) % n])).astype(int)
    if isinstance(item, Mesh):
        edges, faces, hits = _mesh_self_hits(item.vertices, item.faces)
        return np.unique(np.concatenate([edges[hits[:, 0]].ravel(), faces[hits[:, 1]].ravel()])).astype(int)
    raise TypeError(f"expected a Polygon or Mesh, got {type(item).__name__}")


def crossings_between(a, b):
    """Crossings of the boundaries of two polygons or two meshes.

    Returns
    -------
    int
        Crossing edge pairs (2D), or edges of either crossing a triangle of
        the other (3D).
    """
    if isinstance(a, Polygon) and isinstance(b, Polygon):
        va, vb = a.vertices, b.vertices
        return int(np.count_nonzero(segment_crossings(va, np.roll(va, -1, axis=0), vb, np.roll(vb, -1, axis=0))))
    if isinstance(a, Mesh) and isinstance(b, Mesh):
        return _mesh_crossings(_RayMesh(a), _RayMesh(b))
    raise TypeError(f"expected two Polygons or two Meshes, got {type(a).__name__} and {type(b).__name__}")



def overlap_measure(a, b, samples=None):
    """Sampled area (2D, mm^2) or volume (3D, mm^3) inside both ``a`` and ``b``.

    Grid points over the intersection of the two bounding boxes (``samples``
    per axis) are tested inside each item by winding numbers.

    Returns
    -------
    float
        0 when no grid point lies inside both.
    """
    ndim = a.vertices.shape[1]
    (alo, ahi), (blo, bhi) = bounding_box(a.vertices), bounding_box(b.vertices)
    lo, hi = np.maximum(alo, blo), np.minimum(ahi, bhi)
    if np.any(hi <= lo):
        return 0.0
    n = int(samples or OVERLAP_SAMPLES[ndim])
    shape = (n,) * ndim
    extent = tuple(np.stack([lo, hi], axis=1).ravel())
    both = (coverage(a, shape, extent) > 0) & (coverage(b, shape, extent) > 0)
    return float(np.count_nonzero(both) * np.prod((hi - lo) / n))


class _RayMesh:
    """A mesh with its edges and its ray-casting scene, built once for all the pairs it is tested in.

    The intersector is held here, not through ``Trimesh.ray`` (which makes a
    reference cycle, freed only by the garbage collector): a check of hundreds
    of bubbles must free each scene as soon as its last pair is done, or the
    ray-casting library runs out of scenes.
    """

    def __init__(self, mesh):
        self.vertices = np.asarray(mesh.vertices, dtype=float)
        self.edges = _edges(np.asarray(mesh.faces))
        self.mesh = self
        self.ray = _intersector(self.vertices, mesh.faces)


def _mesh_crossings(a, b):
    """Edges of either :class:`_RayMesh` crossing a triangle of the other."""
    return sum(len(_edge_hits(y.mesh, x.vertices[x.edges[:, 0]], x.vertices[x.edges[:, 1]]))
               for x, y in ((a, b), (b, a)))


def _candidate_pairs(fines):
    """Pairs of items whose bounding spheres meet."""
    if len(fines) < 2:
        return []
    centres = np.array([f.vertices.mean(axis=0) for f in fines])
    radii = np.array([np.linalg.norm(f.vertices - c, axis=1).max() for f, c in zip(fines, centres)])
    tree = cKDTree(centres)
    pairs = tree.query_pairs(r=2 * float(radii.max()))
    return sorted((i, j) for i, j in pairs if np.linalg.norm(centres[i] - centres[j]) <= radii[i] + radii[j])


def check_bubbles(items, *, surfaces=("control", "fine"), overlaps=True, only=None):
    """All validity violations of a set of bubbles.

    Parameters
    ----------
    items : sequence of SubdivisionSurface, Polygon or Mesh
        All 2D or all 3D.
    surfaces : tuple of {"control", "fine"}
        Which surfaces of subdivision surfaces to check for self-intersections
        (plain polygons and meshes count as fine).
    overlaps : bool
        Also check pairs of fine surfaces for interpenetration (boundary
        crossings, or one inside the other).
    only : iterable of int, optional
        Check only these bubbles, and the pairs they are in (the others are
        known to be valid: a repair that changed a few bubbles checks those).

    Returns
    -------
    list of Violation
        Empty when every bubble is simple and no two share gas.
    """
    items = list(items)
    only = None if only is None else set(int(k) for k in only)
    out = []
    fines = []
    for i, it in enumerate(items):
        parts = _surfaces_of(it)
        if only is not None and i not in only:
            fines.append(parts[-1][1])
            continue
        for name, s in parts:
            if name in surfaces:
                k = self_crossings(s)
                if k:
                    out.append(Violation("self_intersection", (i,), name, k))
        fine = parts[-1][1]
        size = fine.area if isinstance(fine, Polygon) else fine.volume
        if size <= 0 and not any(v.bubbles == (i,) for v in out):
            out.append(Violation("inverted", (i,), "fine", 0, float(size)))
        fines.append(fine)
    if overlaps:
        pairs = [(i, j) for i, j in _candidate_pairs(fines) if only is None or i in only or j in only]
        last = {}
        for p, pair in enumerate(pairs):
            for b in pair:
                last[b] = p
        rays = {}

        def ray_mesh(i):
            if i not in rays:
                rays[i] = _RayMesh(fines[i])
            return rays[i]

        for p, (i, j) in enumerate(pairs):
            if isinstance(fines[i], Mesh):
                k = _mesh_crossings(ray_mesh(i), ray_mesh(j))
                for b in (i, j):
                    if last[b] == p:
                        rays.pop(b, None)  # its last pair: free its scene now
            else:
                k = crossings_between(fines[i], fines[j])
            area = overlap_measure(fines[i], fines[j])
            if k or area > 0:
                out.append(Violation("overlap", (i, j), "fine", k, area))
    return out
