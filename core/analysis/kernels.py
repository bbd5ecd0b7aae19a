"""Compiled kernels (numba) of the analysis: mesh moments, point-to-mesh distances, volume shared among regions.

* :func:`moments`: volume, area, first and second moments of many closed
  meshes in one pass over their faces (signed tetrahedra about a point of
  each mesh).
* :func:`surface_arrays`, :func:`build_grid`, :func:`query`: the point-to-mesh
  distance. A mesh's triangles are binned into the cells of a uniform grid over its
bounding box that their bounding boxes overlap (:func:`build_grid`), so a
query (:func:`query`) visits only the triangles of the cells within reach of
a point, exactly, whatever the sizes of the triangles. The point-triangle
distance is Ericson's (Real-Time Collision Detection, 5.1.5), and the side
of the surface a point lies on comes from the summed normals of the
triangles sharing its closest point (two at an edge, a fan at a vertex),
which is the right pseudo-normal for closed, consistently oriented meshes.
* :func:`share_volumes`: each bubble's volume cut into slices of its (centre,
  face) tetrahedra, each slice counted in the Cartesian cell and the shell
  holding its centroid (:func:`bubsub.core.analysis.regions.region_volumes`).

Kept at module level so that numba's disk cache hits.
"""

from __future__ import annotations

import numba
import numpy as np

from bubsub.core.projection.backends.jit import cached

__all__ = ["pack", "moments", "surface_arrays", "build_grid", "query", "share_volumes"]

jit = cached(numba.njit, nogil=True, error_model="numpy")


def pack(vertex_arrays, face_arrays):
    """Many meshes as the kernels take them: concatenated vertices (float64) and faces (int64, indices local to
    each mesh), and the start of each mesh's vertices and faces (``n + 1`` entries each)."""
    nv = np.array([len(v) for v in vertex_arrays], dtype=np.int64)
    nf = np.array([len(f) for f in face_arrays], dtype=np.int64)
    vertices = np.ascontiguousarray(np.concatenate([np.asarray(v, dtype=float) for v in vertex_arrays]))
    faces = np.ascontiguousarray(np.concatenate([np.asarray(f, dtype=np.int64) for f in face_arrays]))
    return vertices, faces, np.r_[0, np.cumsum(nv)], np.r_[0, np.cumsum(nf)]


@jit
def _cell_range(lo, hi, origin, cell, dims, out):
    for k in range(3):
        a = int(np.floor((lo[k] - origin[k]) / cell))
        b = int(np.floor((hi[k] - origin[k]) / cell))
        out[k, 0] = min(max(a, 0), dims[k] - 1)
        out[k, 1] = min(max(b, 0), dims[k] - 1)


@jit
def build_grid(tri_lo, tri_hi, origin, cell, dims):
    """Cells -> triangles (CSR) of the triangles' bounding boxes.

    Parameters
    ----------
    tri_lo, tri_hi : (m, 3) float
        Triangle bounding boxes, mm.
    origin : (3,) float
    cell : float
    dims : (3,) int64

    Returns
    -------
    indptr : (cells + 1,) int64
    faces : (entries,) int64
    """
    n_cells = dims[0] * dims[1] * dims[2]
    counts = np.zeros(n_cells + 1, dtype=np.int64)
    r = np.zeros((3, 2), dtype=np.int64)
    for f in range(tri_lo.shape[0]):
        _cell_range(tri_lo[f], tri_hi[f], origin, cell, dims, r)
        for i in range(r[0, 0], r[0, 1] + 1):
            for j in range(r[1, 0], r[1, 1] + 1):
                for k in range(r[2, 0], r[2, 1] + 1):
                    counts[(i * dims[1] + j) * dims[2] + k + 1] += 1
    for c in range(n_cells):
        counts[c + 1] += counts[c]
    faces = np.empty(counts[n_cells], dtype=np.int64)
    fill = counts[:-1].copy()
    for f in range(tri_lo.shape[0]):
        _cell_range(tri_lo[f], tri_hi[f], origin, cell, dims, r)
        for i in range(r[0, 0], r[0, 1] + 1):
            for j in range(r[1, 0], r[1, 1] + 1):
                for k in range(r[2, 0], r[2, 1] + 1):
                    c = (i * dims[1] + j) * dims[2] + k
                    faces[fill[c]] = f
                    fill[c] += 1
    return counts, faces


@jit
def _closest_on_triangle(p, a, b, c, q):
    """Closest point of triangle abc to p, written to q (Ericson)."""
    ab0, ab1, ab2 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    ac0, ac1, ac2 = c[0] - a[0], c[1] - a[1], c[2] - a[2]
    ap0, ap1, ap2 = p[0] - a[0], p[1] - a[1], p[2] - a[2]
    d1 = ab0 * ap0 + ab1 * ap1 + ab2 * ap2
    d2 = ac0 * ap0 + ac1 * ap1 + ac2 * ap2
    if d1 <= 0.0 and d2 <= 0.0:
        q[0], q[1], q[2] = a[0], a[1], a[2]
        return
    bp0, bp1, bp2 = p[0] - b[0], p[1] - b[1], p[2] - b[2]
    d3 = ab0 * bp0 + ab1 * bp1 + ab2 * bp2
    d4 = ac0 * bp0 + ac1 * bp1 + ac2 * bp2
    if d3 >= 0.0 and d4 <= d3:
        q[0], q[1], q[2] = b[0], b[1], b[2]
        return
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        q[0], q[1], q[2] = a[0] + v * ab0, a[1] + v * ab1, a[2] + v * ab2
        return
    cp0, cp1, cp2 = p[0] - c[0], p[1] - c[1], p[2] - c[2]
    d5 = ab0 * cp0 + ab1 * cp1 + ab2 * cp2
    d6 = ac0 * cp0 + ac1 * cp1 + ac2 * cp2
    if d6 >= 0.0 and d5 <= d6:
        q[0], q[1], q[2] = c[0], c[1], c[2]
        return
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        q[0], q[1], q[2] = a[0] + w * ac0, a[1] + w * ac1, a[2] + w * ac2
        return
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        q[0], q[1], q[2] = b[0] + w * (c[0] - b[0]), b[1] + w * (c[1] - b[1]), b[2] + w * (c[2] - b[2])
        return
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    q[0] = a[0] + ab0 * v + ac0 * w
    q[1] = a[1] + ab1 * v + ac1 * w
    q[2] = a[2] + ab2 * v + ac2 * w


@jit
def query(points, reach, vertices, faces, normals, origin, cell, dims, indptr, cell_faces, dist, closest):
    """Signed distance of each point to the mesh where it is at most ``reach``; ``inf`` (and NaN) elsewhere.

    Parameters
    ----------
    points : (k, 3) float
    reach : float
    vertices, faces, normals
        The mesh and its unit face normals.
    origin, cell, dims, indptr, cell_faces
        Its grid (:func:`build_grid`).
    dist : (k,) float, out
        Negative inside.
    closest : (k, 3) float, out
    """
    n_faces = faces.shape[0]
    seen = np.full(n_faces, -1, dtype=np.int64)
    r = np.zeros((3, 2), dtype=np.int64)
    lo = np.empty(3)
    hi = np.empty(3)
    q = np.empty(3)
    best_q = np.empty(3)
    nsum = np.empty(3)
    for s in range(points.shape[0]):
        p = points[s]
        for k in range(3):
            lo[k] = p[k] - reach
            hi[k] = p[k] + reach
        dist[s] = np.inf
        closest[s, 0] = closest[s, 1] = closest[s, 2] = np.nan
        outside = False
        for k in range(3):
            if hi[k] < origin[k] or lo[k] > origin[k] + dims[k] * cell:
                outside = True
        if outside:
            continue
        _cell_range(lo, hi, origin, cell, dims, r)
        best = np.inf
        for i in range(r[0, 0], r[0, 1] + 1):
            for j in range(r[1, 0], r[1, 1] + 1):
                for k in range(r[2, 0], r[2, 1] + 1):
                    c = (i * dims[1] + j) * dims[2] + k
                    for e in range(indptr[c], indptr[c + 1]):
                        f = cell_faces[e]
                        if seen[f] == s:
                            continue
                        seen[f] = s
                        _closest_on_triangle(p, vertices[faces[f, 0]], vertices[faces[f, 1]], vertices[faces[f, 2]],
                                             q)
                        d = np.sqrt((p[0] - q[0]) ** 2 + (p[1] - q[1]) ** 2 + (p[2] - q[2]) ** 2)
                        tol = 1e-9 * (1.0 + d)
                        if d < best - tol:
                            best = d
                            for t in range(3):
                                best_q[t] = q[t]
                                nsum[t] = normals[f, t]
                        elif d <= best + tol:
                            same = (q[0] - best_q[0]) ** 2 + (q[1] - best_q[1]) ** 2 + (q[2] - best_q[2]) ** 2
                            if same <= tol * tol:
                                for t in range(3):
                                    nsum[t] += normals[f, t]
        if best <= reach:
            side = (p[0] - best_q[0]) * nsum[0] + (p[1] - best_q[1]) * nsum[1] + (p[2] - best_q[2]) * nsum[2]
            dist[s] = -best if side < 0.0 else best
            for t in range(3):
                closest[s, t] = best_q[t]


@jit
def moments(vertices, faces, vertex_start, face_start, origins, volume, area, first, second):
    """Per mesh ``k`` (faces ``face_start[k]:face_start[k + 1]``, indices local to its vertices from
    ``vertex_start[k]``): volume, area, ``integral (x - o) dV`` and ``integral (x - o)(x - o)^T dV`` about ``origins[k]``.

    Outputs ``volume``, ``area`` (n,), ``first`` (n, 3), ``second`` (n, 3, 3) are overwritten.
    """
    a = np.empty(3)
    b = np.empty(3)
    c = np.empty(3)
    for m in range(origins.shape[0]):
        vol = 0.0
        ar = 0.0
        f1 = np.zeros(3)
        f2 = np.zeros((3, 3))
        base = vertex_start[m]
        for f in range(face_start[m], face_start[m + 1]):
            for t in range(3):
                a[t] = vertices[base + faces[f, 0], t] - origins[m, t]
                b[t] = vertices[base + faces[f, 1], t] - origins[m, t]
                c[t] = vertices[base + faces[f, 2], t] - origins[m, t]
            det = (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                   + a[2] * (b[0] * c[1] - b[1] * c[0]))
            u0, u1, u2 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
            w0, w1, w2 = c[0] - a[0], c[1] - a[1], c[2] - a[2]
            x0, x1, x2 = u1 * w2 - u2 * w1, u2 * w0 - u0 * w2, u0 * w1 - u1 * w0
            ar += 0.5 * np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
            vol += det
            for i in range(3):
                si = a[i] + b[i] + c[i]
                f1[i] += det * si
                for j in range(i, 3):
                    f2[i, j] += det * (a[i] * a[j] + b[i] * b[j] + c[i] * c[j] + si * (a[j] + b[j] + c[j]))
        volume[m] = vol / 6.0
        area[m] = ar
        for i in range(3):
            first[m, i] = f1[i] / 24.0
            for j in range(i, 3):
                second[m, i, j] = second[m, j, i] = f2[i, j] / 120.0


@jit
def surface_arrays(vertices, faces):
    """Unit face normals (m, 3), vertex areas (a third of their faces' areas, (n,)), face bounding boxes
    (m, 3) x 2 and the median edge length of one closed mesh."""
    m = faces.shape[0]
    normals = np.empty((m, 3))
    vertex_area = np.zeros(vertices.shape[0])
    lo = np.empty((m, 3))
    hi = np.empty((m, 3))
    edges = np.empty(m)
    for f in range(m):
        i, j, k = faces[f, 0], faces[f, 1], faces[f, 2]
        u0, u1, u2 = vertices[j, 0] - vertices[i, 0], vertices[j, 1] - vertices[i, 1], vertices[j, 2] - vertices[i, 2]
        w0, w1, w2 = vertices[k, 0] - vertices[i, 0], vertices[k, 1] - vertices[i, 1], vertices[k, 2] - vertices[i, 2]
        x0, x1, x2 = u1 * w2 - u2 * w1, u2 * w0 - u0 * w2, u0 * w1 - u1 * w0
        twice = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        inv = 1.0 / twice if twice > 0 else 0.0
        normals[f, 0], normals[f, 1], normals[f, 2] = x0 * inv, x1 * inv, x2 * inv
        for v in (i, j, k):
            vertex_area[v] += twice / 6.0
        for t in range(3):
            lo[f, t] = min(vertices[i, t], vertices[j, t], vertices[k, t])
            hi[f, t] = max(vertices[i, t], vertices[j, t], vertices[k, t])
        edges[f] = np.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    return normals, vertex_area, lo, hi, np.median(edges)


@jit
def share_volumes(vertices, faces, vertex_start, face_start, centres, layers, lo, hi, radius, grid, shells,
                  outer_radius, cell_gas, shell_gas):
    """Add each mesh's volume, sliced, to the Cartesian cells and shells of the domain holding the slices.

    Mesh ``k``: faces ``face_start[k]:face_start[k + 1]`` (indices local to its vertices from
    ``vertex_start[k]``), centre ``centres[k]``. Each (centre, face) tetrahedron is cut into ``layers``
    slices parallel to the face; a slice's volume goes to the region holding its centroid, when that lies
    in the domain (box ``lo``-``hi``, and within ``radius`` of the z axis unless ``radius <= 0``).
    ``cell_gas`` ((grid[0] grid[1] grid[2],), k fastest) and ``shell_gas`` ((shells,)) are added to.
    """
    share = np.empty(layers)
    where = np.empty(layers)
    for l in range(layers):
        k1 = (l + 1.0) / layers
        k0 = l / layers
        share[l] = k1 ** 3 - k0 ** 3
        where[l] = 0.75 * (k1 ** 4 - k0 ** 4) / share[l]
    g = np.empty(3)
    p = np.empty(3)
    for m in range(centres.shape[0]):
        base = vertex_start[m]
        for f in range(face_start[m], face_start[m + 1]):
            i, j, k = base + faces[f, 0], base + faces[f, 1], base + faces[f, 2]
            a0, a1, a2 = vertices[i, 0] - centres[m, 0], vertices[i, 1] - centres[m, 1], vertices[i, 2] - centres[m, 2]
            b0, b1, b2 = vertices[j, 0] - centres[m, 0], vertices[j, 1] - centres[m, 1], vertices[j, 2] - centres[m, 2]
            c0, c1, c2 = vertices[k, 0] - centres[m, 0], vertices[k, 1] - centres[m, 1], vertices[k, 2] - centres[m, 2]
            vol = (a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0)) / 6.0
            g[0], g[1], g[2] = (a0 + b0 + c0) / 3.0, (a1 + b1 + c1) / 3.0, (a2 + b2 + c2) / 3.0
            for l in range(layers):
                inside = True
                for t in range(3):
                    p[t] = centres[m, t] + where[l] * g[t]
                    if p[t] < lo[t] or p[t] > hi[t]:
                        inside = False
                r = np.sqrt(p[0] * p[0] + p[1] * p[1])
                if not inside or (radius > 0 and r > radius):
                    continue
                idx = 0
                for t in range(3):
                    q = int(np.floor((p[t] - lo[t]) / (hi[t] - lo[t]) * grid[t]))
                    idx = idx * grid[t] + min(max(q, 0), grid[t] - 1)
                cell_gas[idx] += vol * share[l]
                s = int(np.floor(r / outer_radius * shells))
                shell_gas[min(max(s, 0), shells - 1)] += vol * share[l]
