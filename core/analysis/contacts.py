"""Contacts between bubbles: closest-surface distances of the fine meshes.

Two bubbles are in contact when their surfaces come closer than a gap
(``contact_gap``). Candidate pairs are those whose bounding spheres come that
close (a KD-tree of the sphere centres); for each candidate the distance
between the surfaces is found from both sides: the vertices of one mesh
inside the other's bounding box and sphere grown by the gap are projected
exactly onto the other mesh's triangles that can hold their closest point
(a uniform grid of its triangles, :mod:`bubsub.core.analysis.kernels`).
Only the triangles near a vertex are ever visited, so the cost grows with
the contact area, not with the meshes.

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


#: Most cells of a mesh's triangle grid.
MAX_CELLS = 32768


@dataclass(frozen=True, eq=False)
class Surface:
    """One bubble's fine mesh with what the distance queries need.

    Attributes
    ----------
    vertices : (n, 3) float
        mm.
    faces : (m, 3) int
    vertex_area : (n,) float
        A third of the area of the vertex's triangles, mm^2.
    normals : (m, 3) float
        Unit outward face normals.
    lo, hi : (3,) float
        Bounding box, mm.
    centre : (3,) float
        Centre of the bounding box, mm.
    radius : float
        Bounding-sphere radius about ``centre``, mm.
    grid : tuple
        ``(origin (3,), cell size, dims (3,), indptr, cell faces)``: the triangles binned into a uniform
        grid over the bounding box by their bounding boxes
        (:func:`bubsub.core.analysis.kernels.build_grid`).
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_area: np.ndarray
    normals: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    centre: np.ndarray
    radius: float
    grid: tuple

    @classmethod
    def of(cls, mesh):
        from bubsub.core.analysis.kernels import build_grid, surface_arrays

        v = np.ascontiguousarray(mesh.vertices, dtype=float)
        f = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        normals, area, tri_lo, tri_hi, edge = surface_arrays(v, f)
        lo, hi = v.min(axis=0), v.max(axis=0)
        centre = 0.5 * (lo + hi)
        size = np.maximum(hi - lo, 1e-9)
        cell = max(float(edge), float(np.cbrt(np.prod(size) / MAX_CELLS)))
        dims = np.maximum(1, np.ceil(size / cell)).astype(np.int64)
        indptr, cell_faces = build_grid(tri_lo, tri_hi, lo, cell, dims)
        d = v - centre
        return cls(v, f, area, normals, lo, hi, centre, float(np.sqrt(np.einsum("ij,ij->i", d, d).max())),
                   (lo, cell, dims, indptr, cell_faces))


def surfaces(meshes):
    """:class:`Surface` of each mesh (a list)."""
    return [Surface.of(m) for m in meshes]


def surface_distance(points, surface, reach):
    """Signed distance from points to a closed surface, for the points within ``reach`` of it.

    Exact for any triangle mesh: the triangles binned in the grid cells
    within ``reach`` of a point are all those that can hold its closest point
    (:mod:`bubsub.core.analysis.kernels`); the sign comes from the
    summed normals of the triangles sharing the closest point (the two of an
    edge, the fan of a vertex).

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
    from bubsub.core.analysis.kernels import query

    p = np.ascontiguousarray(np.asarray(points, dtype=float).reshape(-1, 3))
    dist = np.empty(len(p))
    closest = np.empty((len(p), 3))
    if len(p):
        query(p, float(reach), surface.vertices, surface.faces, surface.normals, *surface.grid, dist, closest)
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
    v = a.vertices
    d = v - b.centre
    near = np.all((v >= b.lo - gap) & (v <= b.hi + gap), axis=1) & (np.einsum("ij,ij->i", d, d) <= (b.radius + gap) ** 2)
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
