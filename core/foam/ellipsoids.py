"""Rotated ellipsoids and a cylinder in closed form: contact, ray chords, parallel-beam projections, meshes.

An ellipsoid is a centre ``c``, semi-axes ``a = (a1, a2, a3)`` and a rotation
``R`` (its columns are the principal directions): the points ``x`` with
``(x - c)^T M (x - c) <= 1``, ``M = R diag(a^-2) R^T``. ``S = M^-1 = R diag(a^2) R^T``
is its *shape matrix*: the ellipsoid's half-extent along a unit vector ``e``
is ``sqrt(e^T S e)``.

* :func:`contact_function`: the Perram-Wertheim contact function of two
  ellipsoids (``< 1`` overlap, ``= 1`` touch, ``> 1`` disjoint); it scales with
  the square of the centre distance, so ``|r| / sqrt(F)`` is the centre
  distance at which the two would touch along the same line.
* :func:`ellipsoid_chords`, :func:`cylinder_chords`: the length of arbitrary
  rays inside one ellipsoid / a finite upright cylinder.
* :func:`project_ellipsoids`, :func:`project_cylinder`: parallel-beam
  projections (sum of attenuation x chord) averaged over ``k x k`` sub-rays
  per pixel, at the sub-ray positions of
  :class:`~bubsub.core.projection.projector.MeshProjector`. An ellipsoid is
  evaluated only on the pixels of its shadow's bounding box in each view,
  where its chord is ``2 sqrt(A (1 - Q(w)) + L(w)^2) / A`` for the in-plane
  offset ``w`` of the ray from the centre's ray (``A = r^T M r``,
  ``L = r^T M w``, ``Q = w^T M w``): a quadratic in the pixel coordinates.
* :func:`ellipsoid_mesh`: an icosphere mapped onto the ellipsoid, scaled so
  that the mesh encloses the ellipsoid's exact volume.
* :func:`ellipsoid_labels`: a label image of ellipsoids, testing each voxel
  centre exactly (only within each ellipsoid's bounding box).
* :func:`fraction_below`: the exact fraction of an ellipsoid's volume below a
  horizontal plane (an affine image of a ball's cap).
"""

from __future__ import annotations

import numpy as np

from bubsub.core.foam.checks import unit_icosphere
from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.projection.mesh import Mesh
from bubsub.core.projection.masks import pixel_centres

__all__ = ["shape_matrices", "contact_function", "ellipsoid_chords", "cylinder_chords", "project_ellipsoids",
           "project_cylinder", "ellipsoid_mesh", "fraction_below", "ellipsoid_volumes", "ellipsoid_labels"]

#: Elements of one temporary array of :func:`project_ellipsoids` (views are taken in chunks below this).
_CHUNK = 1 << 21


def shape_matrices(axes, rotations, power=2):
    """``R diag(a**power) R^T`` of each ellipsoid.

    Parameters
    ----------
    axes : (n, 3) float
        Semi-axes, mm.
    rotations : (n, 3, 3) float
        Rotation matrices (columns: principal directions).
    power : float
        2 gives the shape matrices ``S``, -2 the quadratic forms ``M = S^-1``.

    Returns
    -------
    (n, 3, 3) float
    """
    a = np.asarray(axes, dtype=float)
    r = np.asarray(rotations, dtype=float)
    return np.einsum("nij,nj,nkj->nik", r, a**power, r)


def _quad_inverse(m, r):
    """``r^T m^-1 r`` for symmetric 3 x 3 ``m`` (..., 3, 3) and ``r`` (..., 3), by the adjugate."""
    a, b, c = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    d, e, f = m[..., 1, 1], m[..., 1, 2], m[..., 2, 2]
    ca, cb, cc = d * f - e * e, c * e - b * f, b * e - c * d
    cd, ce, cf = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * ca + b * cb + c * cc
    x, y, z = r[..., 0], r[..., 1], r[..., 2]
    return (ca * x * x + cd * y * y + cf * z * z + 2.0 * (cb * x * y + cc * x * z + ce * y * z)) / det


def contact_function(s_i, s_j, r, iterations=40):
    """Perram-Wertheim contact function of pairs of ellipsoids.

    ``F = max over l in [0, 1] of l (1 - l) r^T ((1 - l) S_i + l S_j)^-1 r``, maximised
    by golden-section search (the function is concave in ``l``).

    Parameters
    ----------
    s_i, s_j : (m, 3, 3) float
        Shape matrices (:func:`shape_matrices`) of the two ellipsoids of each pair.
    r : (m, 3) float
        Centre of the second minus centre of the first, mm.
    iterations : int
        Golden-section steps (40 bracket ``l`` to about 1e-8).

    Returns
    -------
    (m,) float
        ``< 1``: the pair overlaps; ``1``: touches; ``> 1``: disjoint.
    """
    s_i, s_j, r = (np.asarray(x, dtype=float) for x in (s_i, s_j, r))

    def value(lam):
        m = (1.0 - lam)[:, None, None] * s_i + lam[:, None, None] * s_j
        return lam * (1.0 - lam) * _quad_inverse(m, r)

    g = (np.sqrt(5.0) - 1.0) / 2.0
    lo, hi = np.zeros(len(r)), np.ones(len(r))
    x1, x2 = hi - g * (hi - lo), lo + g * (hi - lo)
    f1, f2 = value(x1), value(x2)
    for _ in range(iterations):
        right = f1 < f2  # the maximum lies in [x1, hi]
        lo = np.where(right, x1, lo)
        hi = np.where(right, hi, x2)
        new = np.where(right, lo + g * (hi - lo), hi - g * (hi - lo))
        fn = value(new)
        x1, f1, x2, f2 = (np.where(right, x2, new), np.where(right, f2, fn),
                          np.where(right, new, x1), np.where(right, fn, f1))
    return np.maximum(f1, f2)


def ellipsoid_chords(origins, directions, centre, axes, rotation):
    """Length of each ray inside one ellipsoid.

    Parameters
    ----------
    origins, directions : (..., 3) float
        A point on each ray and its direction (any non-zero length), mm.
    centre : (3,) float
    axes : (3,) float
        Semi-axes, mm.
    rotation : (3, 3) float

    Returns
    -------
    (...) float
        mm; 0 for rays that miss.
    """
    o, d = np.asarray(origins, dtype=float), np.asarray(directions, dtype=float)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    m = shape_matrices(np.asarray(axes, dtype=float)[None], np.asarray(rotation, dtype=float)[None], -2)[0]
    q = o - np.asarray(centre, dtype=float)
    md = d @ m
    a = np.einsum("...i,...i->...", md, d)
    b = np.einsum("...i,...i->...", md, q)
    c = np.einsum("...i,ij,...j->...", q, m, q) - 1.0
    disc = b * b - a * c
    return 2.0 * np.sqrt(np.maximum(disc, 0.0)) / a


def cylinder_chords(origins, directions, radius, z_range):
    """Length of each ray inside the upright cylinder ``x^2 + y^2 <= radius^2``, ``z0 <= z <= z1``.

    Parameters
    ----------
    origins, directions : (..., 3) float
        A point on each ray and its direction, mm.
    radius : float
        mm.
    z_range : (z0, z1) float
        mm.

    Returns
    -------
    (...) float
        mm.
    """
    o, d = np.asarray(origins, dtype=float), np.asarray(directions, dtype=float)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    z0, z1 = (float(z) for z in z_range)
    a = d[..., 0] ** 2 + d[..., 1] ** 2
    b = o[..., 0] * d[..., 0] + o[..., 1] * d[..., 1]
    c = o[..., 0] ** 2 + o[..., 1] ** 2 - float(radius) ** 2
    disc = b * b - a * c
    side = a > 0  # not parallel to the axis
    safe_a = np.where(side, a, 1.0)
    root = np.sqrt(np.maximum(disc, 0.0))
    inside = np.where(side, disc >= 0, c <= 0)  # the ray meets the infinite cylinder
    t_in = np.where(side, (-b - root) / safe_a, -np.inf)
    t_out = np.where(side, (-b + root) / safe_a, np.inf)
    flat = d[..., 2] == 0
    dz = np.where(flat, 1.0, d[..., 2])
    ta, tb = (z0 - o[..., 2]) / dz, (z1 - o[..., 2]) / dz
    inside &= ~flat | ((o[..., 2] >= z0) & (o[..., 2] <= z1))
    lo = np.where(flat, -np.inf, np.minimum(ta, tb))
    hi = np.where(flat, np.inf, np.maximum(ta, tb))
    length = np.minimum(t_out, hi) - np.maximum(t_in, lo)
    return np.where(inside, np.maximum(length, 0.0), 0.0)


def _parallel_frames(geometry):
    """Unit rays, detector centres, u and v of a parallel-beam 3D geometry with u, v, ray orthogonal."""
    if not isinstance(geometry, ScanGeometry) or geometry.kind != "parallel3d_vec":
        raise ValueError("the analytic projections need a parallel-beam 3D ScanGeometry (parallel3d_vec)")
    vec = geometry.vectors
    ray = vec[:, 0:3] / np.linalg.norm(vec[:, 0:3], axis=1, keepdims=True)
    det, u, v = vec[:, 3:6], vec[:, 6:9], vec[:, 9:12]
    for x, y, what in ((u, ray, "u and the ray"), (v, ray, "v and the ray"), (u, v, "u and v")):
        cos = np.abs(np.einsum("ij,ij->i", x, y)) / (np.linalg.norm(x, axis=1) * np.linalg.norm(y, axis=1))
        if np.any(cos > 1e-9):
            raise ValueError(f"the analytic projections need orthogonal detector vectors ({what} are not)")
    return ray, det, u, v


def _sub_offsets(k):
    """Sub-ray offsets within a pixel, as MeshProjector and ScanGeometry.rays place them."""
    return (np.arange(k) + 0.5) / k - 0.5


def project_ellipsoids(geometry, centres, axes, rotations, attenuation, supersampling=2, out=None):
    """Parallel-beam projection of disjoint or overlapping ellipsoids, exact per sub-ray.

    Parameters
    ----------
    geometry : ScanGeometry
        ``parallel3d_vec`` with the ray, u and v of each projection orthogonal
        (:meth:`ScanGeometry.parallel`).
    centres : (n, 3) float
    axes : (n, 3) float
        Semi-axes, mm.
    rotations : (n, 3, 3) float
    attenuation : float or (n,) float
        1/mm, per ellipsoid.
    supersampling : int
        ``k``: ``k x k`` sub-rays per pixel, their line integrals averaged.
    out : ndarray float64 of ``geometry.shape``, optional
        Added to (and returned).

    Returns
    -------
    ndarray float64, ``geometry.shape``
        Line integrals.
    """
    ray, det, u, v = _parallel_frames(geometry)
    n_views, rows, cols = geometry.shape
    k = int(supersampling)
    if k < 1:
        raise ValueError(f"supersampling must be a positive integer, got {supersampling!r}")
    c = np.atleast_2d(np.asarray(centres, dtype=float))
    a = np.atleast_2d(np.asarray(axes, dtype=float))
    rot = np.asarray(rotations, dtype=float).reshape(-1, 3, 3)
    mu = np.broadcast_to(np.asarray(attenuation, dtype=float), (len(c),))
    if not (len(a) == len(c) == len(rot)) or np.any(a <= 0):
        raise ValueError("centres, axes and rotations must describe the same ellipsoids, with positive axes")
    out = np.zeros(geometry.shape) if out is None else out
    nu, nv = np.linalg.norm(u, axis=1), np.linalg.norm(v, axis=1)
    uh, vh = u / nu[:, None], v / nv[:, None]
    off = _sub_offsets(k)
    big_m, big_s = shape_matrices(a, rot, -2), shape_matrices(a, rot, 2)
    for b in range(len(c)):
        m, s = big_m[b], big_s[b]
        rel = c[b] - det
        col_c = np.einsum("ij,ij->i", rel, u) / nu**2 + cols / 2 - 0.5  # pixel-index coordinates of the centre
        row_c = np.einsum("ij,ij->i", rel, v) / nv**2 + rows / 2 - 0.5
        half_u = np.sqrt(np.einsum("ij,jk,ik->i", uh, s, uh)) / nu  # shadow half-extents, pixels
        half_v = np.sqrt(np.einsum("ij,jk,ik->i", vh, s, vh)) / nv
        j0, j1 = np.ceil(col_c - half_u - 0.5).astype(int), np.floor(col_c + half_u + 0.5).astype(int)
        i0, i1 = np.ceil(row_c - half_v - 0.5).astype(int), np.floor(row_c + half_v + 0.5).astype(int)
        seen = (j1 >= 0) & (j0 < cols) & (i1 >= 0) & (i0 < rows)
        if not seen.any():
            continue
        i0, i1 = np.maximum(i0, 0), np.minimum(i1, rows - 1)  # rows off the detector are never needed
        j0, j1 = np.maximum(j0, 0), np.minimum(j1, cols - 1)
        views = np.flatnonzero(seen & (i1 >= i0) & (j1 >= j0))
        width, height = int((j1 - j0)[views].max()) + 1, int((i1 - i0)[views].max()) + 1
        mr = ray @ m
        big_a = np.einsum("ij,ij->i", mr, ray)
        m_ru, m_rv = np.einsum("ij,ij->i", mr, uh), np.einsum("ij,ij->i", mr, vh)
        m_uu = np.einsum("ij,jk,ik->i", uh, m, uh)
        m_uv = np.einsum("ij,jk,ik->i", uh, m, vh)
        m_vv = np.einsum("ij,jk,ik->i", vh, m, vh)
        k_ss, k_st, k_tt = m_ru**2 - big_a * m_uu, m_ru * m_rv - big_a * m_uv, m_rv**2 - big_a * m_vv
        step = max(1, _CHUNK // (height * width * k * k))
        for start in range(0, len(views), step):
            w = views[start:start + step]
            s_mm = ((j0[w, None] + (np.arange(width)[:, None] + off).ravel()[None, :]) - col_c[w, None]) * nu[w, None]
            t_mm = ((i0[w, None] + (np.arange(height)[:, None] + off).ravel()[None, :]) - row_c[w, None]) * nv[w, None]
            disc = (big_a[w, None, None] + (k_ss[w, None] * s_mm**2)[:, None, :]
                    + (k_tt[w, None] * t_mm**2)[:, :, None]
                    + 2.0 * k_st[w, None, None] * t_mm[:, :, None] * s_mm[:, None, :])
            chord = np.sqrt(np.maximum(disc, 0.0, out=disc), out=disc)
            chord *= (2.0 * mu[b] / (k * k)) / big_a[w, None, None]
            pix = chord.reshape(len(w), height, k, width, k).sum(axis=(2, 4))
            for n, view in enumerate(w):
                hh, ww = i1[view] - i0[view] + 1, j1[view] - j0[view] + 1
                out[view, i0[view]:i1[view] + 1, j0[view]:j1[view] + 1] += pix[n, :hh, :ww]
    return out


def project_cylinder(geometry, radius, z_range, attenuation, supersampling=2):
    """Parallel-beam projection of the upright cylinder of :func:`cylinder_chords`, ``k x k`` sub-rays per pixel.

    Returns
    -------
    ndarray float64, ``geometry.shape``
        ``attenuation`` x mean sub-ray chord.
    """
    ray, det, u, v = _parallel_frames(geometry)
    _, rows, cols = geometry.shape
    k = int(supersampling)
    off = _sub_offsets(k)
    sub_c = (np.arange(cols)[:, None] - cols / 2 + 0.5 + off).ravel()  # sub-ray positions, pixels
    sub_r = (np.arange(rows)[:, None] - rows / 2 + 0.5 + off).ravel()
    out = np.empty(geometry.shape)
    for view in range(geometry.n_angles):
        if ray[view, 2] == 0 and u[view, 2] == 0 and not v[view, :2].any():
            # horizontal rays, vertical v: the chord is the disc's chord at the column, if the row is in z_range
            o = det[view] + sub_c[:, None] * u[view]
            z = det[view, 2] + sub_r * v[view, 2]
            inside = ((z >= z_range[0]) & (z <= z_range[1])).astype(float)
            flat = cylinder_chords(o, np.broadcast_to(ray[view], o.shape), radius, (-np.inf, np.inf))
            chords = inside[:, None] * flat[None, :]
        else:
            o = det[view] + sub_r[:, None, None] * v[view] + sub_c[None, :, None] * u[view]
            chords = cylinder_chords(o, np.broadcast_to(ray[view], o.shape), radius, z_range)
        out[view] = attenuation * chords.reshape(rows, k, cols, k).mean(axis=(1, 3))
    return out


_UNIT_MESHES = {}


def _unit_mesh(subdivisions):
    """(vertices, faces) of an icosphere scaled so that it encloses 4 pi / 3 exactly."""
    if subdivisions not in _UNIT_MESHES:
        v, f = unit_icosphere(subdivisions)
        tri = v[f]
        vol = np.einsum("ij,ij->", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
        _UNIT_MESHES[subdivisions] = (v * np.cbrt(4.0 * np.pi / 3.0 / vol), f)
    return _UNIT_MESHES[subdivisions]


def ellipsoid_mesh(centre, axes, rotation, attenuation, subdivisions=4, *, template=None):
    """A closed mesh of an ellipsoid enclosing its exact volume ``4/3 pi a1 a2 a3``.

    The vertices of an icosphere with ``20 * 4**subdivisions`` triangles,
    pushed slightly outside the unit sphere so that the mesh's volume is the
    ball's, are mapped by ``x -> c + R diag(a) x``: the vertices lie about
    ``0.0029 a_max / 4**(subdivisions - 3)`` outside the ellipsoid, the face
    centres about ``0.0017 a_max / 4**(subdivisions - 3)`` inside it.

    Parameters
    ----------
    centre : (3,) float
    axes : (3,) float
    rotation : (3, 3) float
    attenuation : float
    subdivisions : int
    template : Mesh, optional
        A mesh of this icosphere (any vertices) whose validated faces are reused.

    Returns
    -------
    Mesh
    """
    unit, faces = _unit_mesh(subdivisions)
    verts = np.asarray(centre, dtype=float) + (unit * np.asarray(axes, dtype=float)) @ np.asarray(rotation).T
    if template is not None:
        return template.with_vertices(verts).with_attenuation(attenuation)
    return Mesh(verts, faces, attenuation)


def ellipsoid_volumes(axes):
    """``4/3 pi a1 a2 a3`` of each ellipsoid, (n,) mm^3."""
    return 4.0 / 3.0 * np.pi * np.prod(np.atleast_2d(axes), axis=1)


def fraction_below(centres, shapes, z):
    """Exact fraction of each ellipsoid's volume below the plane ``z``.

    The ellipsoid is the affine image of the unit ball, and the plane maps to a
    plane at signed distance ``t = (z - c_z) / sqrt(S_zz)`` from the ball's
    centre, so the fraction is the ball's cap fraction ``(1 + t)^2 (2 - t) / 4``.

    Parameters
    ----------
    centres : (n, 3) float
    shapes : (n, 3, 3) float
        Shape matrices (:func:`shape_matrices`).
    z : float
        mm.

    Returns
    -------
    (n,) float in [0, 1]
    """
    t = np.clip((float(z) - np.asarray(centres)[:, 2]) / np.sqrt(np.asarray(shapes)[:, 2, 2]), -1.0, 1.0)
    return (1.0 + t) ** 2 * (2.0 - t) / 4.0


def ellipsoid_labels(centres, axes, rotations, shape, extent):
    """Label image of ellipsoids: voxel centres inside ellipsoid ``i`` get ``i + 1``, the rest 0.

    Parameters
    ----------
    centres, axes : (n, 3) float
        mm.
    rotations : (n, 3, 3) float
    shape : (slices, rows, cols)
    extent : (xmin, xmax, ymin, ymax, zmin, zmax)
        The grid convention of :mod:`bubsub.core.projection.masks` (``vol[z, y, x]``, y decreasing with the row).

    Returns
    -------
    (slices, rows, cols) int32
        Where ellipsoids overlap, the later one wins.
    """
    z, y, x = pixel_centres(shape, extent)
    c = np.atleast_2d(np.asarray(centres, dtype=float))
    m, s = shape_matrices(axes, rotations, -2), shape_matrices(axes, rotations, 2)
    half = np.sqrt(np.diagonal(s, axis1=1, axis2=2))
    out = np.zeros(tuple(shape), dtype=np.int32)
    for b in range(len(c)):
        zi, yi, xi = (np.flatnonzero(np.abs(t - c[b, k]) <= half[b, k]) for t, k in ((z, 2), (y, 1), (x, 0)))
        if not (len(zi) and len(yi) and len(xi)):
            continue
        q = [z[zi][:, None, None] - c[b, 2], y[yi][None, :, None] - c[b, 1], x[xi][None, None, :] - c[b, 0]]
        mb = m[b][::-1, ::-1]  # (z, y, x) order
        form = sum(mb[i, j] * q[i] * q[j] for i in range(3) for j in range(3))
        box = out[zi[0]:zi[-1] + 1, yi[0]:yi[-1] + 1, xi[0]:xi[-1] + 1]  # y indices are contiguous too
        box[form <= 1.0] = b + 1
    return out
