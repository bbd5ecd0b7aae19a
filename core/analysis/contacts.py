"""Contacts between bubbles: closest-surface distances of the fine meshes.

Two bubbles are in contact when their surfaces come closer than a gap
(``contact_gap``). Candidate pairs are those whose bounding spheres come that
close (a KD-tree of the sphere centres); for each candidate the distance
between the surfaces is found from both sides: the vertices of one mesh that
can be within the gap of the other (a bound from a KD-tree of the other
mesh's vertices) are projected exactly onto the other mesh's triangles that
can hold their closest point (a KD-tree of its triangle centroids;
``trimesh.triangles.closest_point``). Only the vertices near a contact are
ever projected, so the cost grows with the contact area, not with the meshes.

For a contact the result gives

* ``gap``: the closest distance between the two surfaces, mm; negative (the
  deepest vertex's depth) when the meshes interpenetrate;
* the contact point: the middle of the closest pair of points;
* the branch vector: centroid of the second bubble minus that of the first;
* the film area: the near-contact area, the mean over both bubbles of their
  surface area (one third of each triangle's area per vertex) lying closer
  than the gap to the other bubble.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["Surface", "surfaces", "find_contacts", "Contacts", "surface_distance", "CONTACT_COLUMN_INFO"]


#: Face groups up to this size are tested by their bounding boxes rather than through a KD-tree.
SMALL_GROUP = 256


@dataclass(frozen=True, eq=False)
class Surface:
    """One bubble's fine mesh with what the distance queries need.

    Attributes
    ----------
    vertices : (n, 3) float
        mm.
    faces : (m, 3) int
    tree : scipy.spatial.cKDTree
        Of the vertices.
    vertex_area : (n,) float
        A third of the area of the vertex's triangles, mm^2.
    normals : (m, 3) float
        Unit outward face normals.
    face_groups : list of (scipy.spatial.cKDTree or None, float, (g,) int, (g, 3) float, (g, 3) float)
        The faces grouped by size (centroid-to-corner distance, in factors of two): a
        KD-tree of the group's centroids (None for a group of at most :data:`SMALL_GROUP`
        faces, tested by their bounding boxes), its largest such distance (mm), the faces,
        and their bounding boxes' corners (mm).
    centre : (3,) float
        Centre of the bounding box, mm.
    radius : float
        Bounding-sphere radius about ``centre``, mm.
    edge : float
        Longest edge, mm.
    """

    vertices: np.ndarray
    faces: np.ndarray
    tree: cKDTree
    vertex_area: np.ndarray
    normals: np.ndarray
    face_groups: list
    centre: np.ndarray
    radius: float
    edge: float

    @classmethod
    def of(cls, mesh):
        v = np.asarray(mesh.vertices, dtype=float)
        f = np.asarray(mesh.faces, dtype=np.int64)
        tri = v[f]
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        twice = np.linalg.norm(cross, axis=1)
        normals = cross / np.maximum(twice, 1e-300)[:, None]
        area = np.bincount(f.ravel(), weights=np.repeat(twice / 6.0, 3), minlength=len(v))
        edges = np.linalg.norm(tri - tri[:, [1, 2, 0]], axis=2)
        lo, hi = v.min(axis=0), v.max(axis=0)
        centre = 0.5 * (lo + hi)
        mid = tri.mean(axis=1)
        spread = np.linalg.norm(tri - mid[:, None, :], axis=2).max(axis=1)
        base = max(float(spread.min()), 1e-3 * float(np.median(spread)))
        level = np.floor(np.log2(np.maximum(spread / max(base, 1e-300), 1.0))).astype(int)
        groups = []
        for k in np.unique(level):
            sel = np.nonzero(level == k)[0]
            tree = cKDTree(mid[sel]) if len(sel) > SMALL_GROUP else None
            groups.append((tree, float(spread[sel].max()), sel, tri[sel].min(axis=1), tri[sel].max(axis=1)))
        return cls(v, f, cKDTree(v), area, normals, groups, centre, float(np.linalg.norm(v - centre, axis=1).max()),
                   float(edges.max()))


def surfaces(meshes):
    """:class:`Surface` of each mesh (a list)."""
    return [Surface.of(m) for m in meshes]


def surface_distance(points, surface, reach):
    """Signed distance from points to a closed surface, for the points within ``reach`` of it.

    Exact for any triangle mesh. A point within ``reach`` of the surface has
    its closest point on a triangle whose centroid is within ``reach`` plus
    the triangle's centroid-to-corner distance; the triangles are grouped by
    that size (:attr:`Surface.face_groups`), so a query visits the small
    triangles near the point and the few large ones (by their bounding
    boxes), whatever the mesh's uniformity. The sign comes from the summed normals of the triangles
    sharing the closest point (the two of an edge, the fan of a vertex).

    Parameters
    ----------
    points : (k, 3) float
        mm.
    surface : Surface
    reach : float
        mm.

    Returns
    -------
    distance : (k,) float
        mm; negative inside the surface; ``inf`` for the points farther than ``reach``.
    closest : (k, 3) float
        The closest point of the surface (NaN for those points).
    """
    from trimesh.triangles import closest_point

    p = np.asarray(points, dtype=float).reshape(-1, 3)
    dist = np.full(len(p), np.inf)
    closest = np.full((len(p), 3), np.nan)
    if not len(p):
        return dist, closest
    d_v, _ = surface.tree.query(p, k=1, distance_upper_bound=reach + surface.edge)
    rows = np.nonzero(np.isfinite(d_v))[0]  # a nearer vertex than reach + the longest edge: maybe within reach
    if not len(rows):
        return dist, closest
    pts = p[rows]
    pair_point, pair_face = [], []
    for tree, radius, faces, lo, hi in surface.face_groups:
        if tree is None:  # a few (large) faces: their bounding boxes, within reach of the point
            near = np.all((pts[:, None, :] >= lo[None] - reach) & (pts[:, None, :] <= hi[None] + reach), axis=2)
            k, j = np.nonzero(near)
            pair_point.append(k)
            pair_face.append(faces[j])
            continue
        lists = tree.query_ball_point(pts, r=reach + radius)
        counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(pts))
        if counts.sum():
            pair_point.append(np.repeat(np.arange(len(pts)), counts))
            pair_face.append(faces[np.fromiter((f for x in lists for f in x), dtype=np.int64, count=int(counts.sum()))])
    if pair_point:
        pair_point, pair_face = np.concatenate(pair_point), np.concatenate(pair_face)
    if not len(pair_point):
        return dist, closest
    order = np.argsort(pair_point, kind="stable")
    pair_point, pair_face = pair_point[order], pair_face[order]
    q = closest_point(surface.vertices[surface.faces[pair_face]], pts[pair_point])
    dd = np.linalg.norm(pts[pair_point] - q, axis=1)
    found, start = np.unique(pair_point, return_index=True)
    best = np.full(len(pts), np.inf)
    best[found] = np.minimum.reduceat(dd, start)
    # one closest point per point; the faces sharing it (the two of an edge, the fan of a vertex) give the side
    tol = 1e-9 * (1.0 + best[pair_point])
    tied = np.nonzero(dd <= best[pair_point] + tol)[0]
    first = tied[np.unique(pair_point[tied], return_index=True)[1]]
    q_best = np.full((len(pts), 3), np.nan)
    q_best[pair_point[first]] = q[first]
    same = np.linalg.norm(q - q_best[pair_point], axis=1) <= tol
    normal = np.zeros((len(pts), 3))
    np.add.at(normal, pair_point[same], surface.normals[pair_face[same]])
    within = best <= reach
    inside = np.einsum("ij,ij->i", pts - q_best, normal) < 0
    dist[rows[within]] = np.where(inside, -best, best)[within]
    closest[rows[within]] = q_best[within]
    return dist, closest


@dataclass(frozen=True)
class Contacts:
    """Contacts between bubbles (indices into the list of meshes).

    Attributes
    ----------
    pairs : (k, 2) int
        Bubble indices ``a < b``.
    gap : (k,) float
        Closest surface distance, mm (negative: interpenetration depth).
    point : (k, 3) float
        Contact point, mm.
    film_area : (k,) float
        Near-contact area, mm^2.
    """

    pairs: np.ndarray
    gap: np.ndarray
    point: np.ndarray
    film_area: np.ndarray

    def __len__(self):
        return len(self.pairs)

    def coordination(self, n):
        """Number of contacts of each of ``n`` bubbles, (n,) int."""
        return np.bincount(self.pairs.ravel(), minlength=n).astype(int)


def _side(a, b, gap):
    """Distances of ``a``'s vertices that may lie within ``gap`` of ``b``: (indices, signed distances, closest)."""
    near = np.linalg.norm(a.vertices - b.centre, axis=1) <= b.radius + gap + b.edge
    idx = np.nonzero(near)[0]
    d, q = surface_distance(a.vertices[idx], b, gap)
    return idx, d, q


def find_contacts(items, gap):
    """All pairs of bubbles whose surfaces come closer than ``gap``.

    Parameters
    ----------
    items : sequence of Mesh or of Surface
        Closed, outward fine meshes (Surfaces are reused, e.g. across gaps).
    gap : float
        Contact gap, mm (> 0).

    Returns
    -------
    Contacts
        Sorted by pair.
    """
    gap = float(gap)
    if not gap > 0 or not np.isfinite(gap):
        raise ValueError(f"the contact gap must be positive and finite, got {gap!r} mm")
    surfs = [s if isinstance(s, Surface) else Surface.of(s) for s in items]
    n = len(surfs)
    empty = Contacts(np.zeros((0, 2), int), np.zeros(0), np.zeros((0, 3)), np.zeros(0))
    if n < 2:
        return empty
    centre = np.array([s.centre for s in surfs])
    radius = np.array([s.radius for s in surfs])
    cand = cKDTree(centre).query_pairs(2 * radius.max() + gap, output_type="ndarray")
    if len(cand):
        i, j = cand[:, 0], cand[:, 1]
        cand = cand[np.linalg.norm(centre[i] - centre[j], axis=1) < radius[i] + radius[j] + gap]
    pairs, gaps, points, films = [], [], [], []
    for i, j in sorted(map(tuple, np.sort(cand, axis=1))):
        a, b = surfs[i], surfs[j]
        ia, da, qa = _side(a, b, gap)
        ib, db, qb = _side(b, a, gap)
        best_a = np.min(da) if len(da) else np.inf
        best_b = np.min(db) if len(db) else np.inf
        g = min(best_a, best_b)
        if not g < gap:
            continue
        if best_a <= best_b:
            k = int(np.argmin(da))
            point = 0.5 * (a.vertices[ia[k]] + qa[k])
        else:
            k = int(np.argmin(db))
            point = 0.5 * (b.vertices[ib[k]] + qb[k])
        film = 0.5 * (a.vertex_area[ia[da < gap]].sum() + b.vertex_area[ib[db < gap]].sum())
        pairs.append((i, j))
        gaps.append(g)
        points.append(point)
        films.append(film)
    if not pairs:
        return empty
    return Contacts(np.array(pairs, dtype=int), np.array(gaps), np.array(points), np.array(films))


#: ``column: (unit, meaning)`` of ``contacts.csv``.
CONTACT_COLUMN_INFO = {
    "id_a": ("", "bubble id (bubble_id of bubbles.ply) of the first bubble, the smaller id"),
    "id_b": ("", "bubble id of the second bubble"),
    "gap_mm": ("mm", "closest distance between the two refined surfaces (negative: they interpenetrate by this "
                     "much)"),
    **{f"contact_{a}_mm": ("mm", f"{a} coordinate of the contact point, the middle of the closest pair of points")
       for a in "xyz"},
    **{f"branch_{a}_mm": ("mm", f"{a} component of the branch vector, centroid of id_b minus centroid of id_a")
       for a in "xyz"},
    "branch_length_mm": ("mm", "length of the branch vector (distance between the centroids)"),
    "film_area_mm2": ("mm^2", "near-contact (film) area: the mean over the two bubbles of their surface area "
                              "closer than the contact gap to the other bubble"),
}
