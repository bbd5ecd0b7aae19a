"""Rasterisation of closed polygons (2D) and closed triangle meshes (3D) on voxel grids.

This is the one place where bubsub turns shapes into pixels: the phantoms'
attenuation images, ground-truth masks and the binarised reconstructions
compared with the Dice dissimilarity all come from here.

Grids follow the image convention of ``docs/architecture.md``:

* 2D: ``img[row, col]`` of shape ``(rows, cols)`` on ``extent = (xmin, xmax,
  ymin, ymax)``; pixel centre ``x = xmin + (col + 0.5) * dx``,
  ``y = ymax - (row + 0.5) * dy`` (row 0 at y max), ``dx = (xmax - xmin) /
  cols``, ``dy = (ymax - ymin) / rows``. This matches ASTRA's 2D
  ``create_vol_geom(rows, cols, xmin, xmax, ymin, ymax)``.
* 3D: ``vol[z, y, x]`` of shape ``(slices, rows, cols)`` on ``extent = (xmin,
  xmax, ymin, ymax, zmin, zmax)``; x and y within a slice as in 2D, and
  ``z = zmin + (slice + 0.5) * dz``.

Algorithm: exact point-in-shape tests of the pixel (voxel) centres by
counting signed crossings of rays along +x, one ray per grid row, with
half-open tie rules so that a centre lying exactly on an edge, a vertex or
a shared triangle edge is counted consistently (never twice, never lost).
The crossings are scattered into a difference array and summed along x,
which gives the winding number of every centre at once; only the bounding
box of each shape is visited. A 200 x 200 x 100 grid with a hundred
320-triangle bubbles takes well under a second.

With ``supersample=s`` each pixel is tested at ``s**d`` sub-pixel centres
(a regular grid) and the result is the covered fraction.
"""

from __future__ import annotations

import numbers

import numpy as np

from bubsub.core.projection.mesh import Mesh, Polygon
from bubsub.core.projection.items import resolve_items
from bubsub.core.validate import check_int

__all__ = ["check_grid", "pixel_centres", "rasterize", "label_image", "bubble_mask", "coverage"]

# Upper bound on (candidate ray, triangle) pairs handled in one vectorised batch.
_BATCH = 2_000_000


# -- grids ---------------------------------------------------------------------
def check_grid(shape, extent):
    """Validate a grid.

    Parameters
    ----------
    shape : (rows, cols) or (slices, rows, cols) ints
    extent : (xmin, xmax, ymin, ymax) or (xmin, xmax, ymin, ymax, zmin, zmax) floats
        In mm; ``len(extent) == 2 * len(shape)``.

    Returns
    -------
    shape : tuple of int
    extent : tuple of float

    Raises
    ------
    ValueError
        If the shape has the wrong length or non-positive entries, or the
        extent has the wrong length, non-finite values or an empty range.
    """
    try:
        shp = tuple(shape)
    except TypeError:
        raise ValueError(f"grid shape must be a tuple (rows, cols) or (slices, rows, cols), got {shape!r}") from None
    if len(shp) not in (2, 3):
        raise ValueError(f"grid shape must have 2 or 3 entries, got {shp!r}")
    for s in shp:
        if isinstance(s, bool) or not isinstance(s, numbers.Integral) or s < 1:
            raise ValueError(f"grid shape entries must be positive integers, got {shp!r}")
    shp = tuple(int(s) for s in shp)
    try:
        ext = tuple(float(e) for e in extent)
    except (TypeError, ValueError):
        raise ValueError(f"grid extent must be a sequence of numbers, got {extent!r}") from None
    if len(ext) != 2 * len(shp):
        names = "(xmin, xmax, ymin, ymax)" if len(shp) == 2 else "(xmin, xmax, ymin, ymax, zmin, zmax)"
        raise ValueError(f"grid extent for a {len(shp)}D shape must be {names}, got {len(ext)} values")
    if not all(np.isfinite(ext)):
        raise ValueError(f"grid extent must be finite, got {ext!r}")
    for axis, (lo, hi) in zip("xyz", zip(ext[0::2], ext[1::2])):
        if not hi > lo:
            raise ValueError(f"grid extent has an empty {axis} range: {axis}min={lo} >= {axis}max={hi}")
    return shp, ext


def pixel_centres(shape, extent):
    """Pixel (voxel) centre coordinates along each axis of a grid.

    Parameters
    ----------
    shape : (rows, cols) or (slices, rows, cols)
    extent : (xmin, xmax, ymin, ymax[, zmin, zmax])

    Returns
    -------
    tuple of 1D float arrays
        ``(y, x)`` for 2D, ``(z, y, x)`` for 3D, one array per array axis,
        of lengths ``shape``; ``y`` decreases with the row index.
    """
    shp, ext = check_grid(shape, extent)
    x = _x_centres(shp[-1], ext[0], ext[1])
    y = _y_centres(shp[-2], ext[2], ext[3])
    if len(shp) == 2:
        return y, x
    z = _x_centres(shp[0], ext[4], ext[5])
    return z, y, x


def _x_centres(n, lo, hi, start=0, stop=None):
    """Centres of cells start..stop-1 of n along an increasing axis (also used for z)."""
    stop = n if stop is None else stop
    return lo + (np.arange(start, stop) + 0.5) * ((hi - lo) / n)


def _y_centres(n, lo, hi, start=0, stop=None):
    """Centres of rows start..stop-1 of n, row 0 at the top (y max)."""
    stop = n if stop is None else stop
    return hi - (np.arange(start, stop) + 0.5) * ((hi - lo) / n)


# -- items ---------------------------------------------------------------------
def _as_items(items, ndim):
    """A list of Polygon (ndim 2) or Mesh (ndim 3); SubdivisionSurfaces are refined."""
    want = Polygon if ndim == 2 else Mesh
    return resolve_items(items, want, "items", hint=f" (a {ndim}D grid takes {want.__name__} items, or "
                                                    f"SubdivisionSurfaces of them)")


def _supersample(supersample):
    check_int(supersample, "supersample", 1)
    return int(supersample)


def _bbox(lo, hi, ext_lo, ext_hi, n, flip=False):
    """Half-open index range of the cells that can hold centres inside [lo, hi]."""
    d = (ext_hi - ext_lo) / n
    if flip:  # rows: index grows as y decreases
        lo, hi = ext_hi - hi, ext_hi - lo
    else:
        lo, hi = lo - ext_lo, hi - ext_lo
    a = int(np.clip(np.floor(lo / d) - 1, 0, n))
    b = int(np.clip(np.floor(hi / d) + 2, 0, n))
    return a, b


# -- 2D: crossings of polygon edges with horizontal rays -----------------------------
def _winding_polygon(vertices, ys, x0, dx, nx):
    """Winding numbers of the centres of a sub-grid with respect to a closed polygon.

    Parameters
    ----------
    vertices : (n, 2) float
    ys : (ny,) float
        y of each grid row (any order).
    x0, dx, nx :
        Column centres ``x0 + i * dx`` for ``i < nx``.

    Returns
    -------
    (ny, nx) int32
    """
    a = vertices
    b = np.roll(vertices, -1, axis=0)
    ay, by = a[:, 1], b[:, 1]
    ylo, yhi = np.minimum(ay, by), np.maximum(ay, by)
    # rows whose y lies in [ylo, yhi): candidates via sorting, checked exactly below
    order = np.argsort(ys, kind="stable")
    ys_sorted = ys[order]
    first = np.searchsorted(ys_sorted, ylo, side="left")
    last = np.searchsorted(ys_sorted, yhi, side="left")
    counts = last - first
    keep = counts > 0
    edge = np.repeat(np.nonzero(keep)[0], counts[keep])
    offs = np.arange(edge.size) - np.repeat(np.cumsum(counts[keep]) - counts[keep], counts[keep])
    row = order[np.repeat(first[keep], counts[keep]) + offs]
    y = ys[row]
    # half-open test: exactly one end strictly above the ray
    ok = (ay[edge] > y) != (by[edge] > y)
    edge, row, y = edge[ok], row[ok], y[ok]
    ax, bx = a[edge, 0], b[edge, 0]
    t = (y - ay[edge]) / (by[edge] - ay[edge])
    xc = ax + t * (bx - ax)
    # entering (+1) where the boundary runs downwards (counter-clockwise => interior on the left)
    w = np.where(by[edge] < ay[edge], 1, -1).astype(np.int32)
    return _accumulate(row, xc, w, len(ys), x0, dx, nx)


def _accumulate(row, xc, w, ny, x0, dx, nx):
    """Winding numbers from signed crossings ``(row, x)`` of rays along +x."""
    i0 = np.ceil((xc - x0) / dx).astype(np.int64)
    np.clip(i0, 0, nx, out=i0)
    diff = np.zeros(ny * (nx + 1), dtype=np.int32)
    np.add.at(diff, row * (nx + 1) + i0, w)
    wind = np.cumsum(diff.reshape(ny, nx + 1), axis=1, dtype=np.int32)
    return wind[:, :nx]


# -- 3D: crossings of triangles with rays along +x ------------------------------------
def _winding_mesh(vertices, faces, zs, ys, x0, dx, nx):
    """Winding numbers of the centres of a sub-grid with respect to a closed mesh.

    Parameters
    ----------
    vertices : (n, 3) float
    faces : (m, 3) int
    zs : (nz,) float
        Increasing slice centres.
    ys : (ny,) float
        Row centres (decreasing, image convention).
    x0, dx, nx :
        Column centres ``x0 + i * dx``.

    Returns
    -------
    (nz, ny, nx) int32
    """
    nz, ny = len(zs), len(ys)
    P = vertices[:, 1:3]  # (y, z) projections
    f = np.asarray(faces, dtype=np.int64)
    p, q, r = P[f[:, 0]], P[f[:, 1]], P[f[:, 2]]
    nxs = (q[:, 0] - p[:, 0]) * (r[:, 1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (r[:, 0] - p[:, 0])
    live = nxs != 0  # triangles seen edge-on by the rays cross nothing
    f, nxs = f[live], nxs[live]
    if len(f) == 0:
        return np.zeros((nz, ny, nx), dtype=np.int32)
    sigma = np.sign(nxs)
    Pf = P[f]  # (m, 3, 2)
    zmin, zmax = Pf[:, :, 1].min(axis=1), Pf[:, :, 1].max(axis=1)
    ymin, ymax = Pf[:, :, 0].min(axis=1), Pf[:, :, 0].max(axis=1)
    dz = zs[1] - zs[0] if nz > 1 else 1.0
    dy = ys[0] - ys[1] if ny > 1 else 1.0
    # index ranges (inclusive-exclusive, padded by one, verified exactly later)
    k0 = np.clip(np.floor((zmin - zs[0]) / dz).astype(np.int64), 0, nz)
    k1 = np.clip(np.floor((zmax - zs[0]) / dz).astype(np.int64) + 2, 0, nz)
    j0 = np.clip(np.floor((ys[0] - ymax) / dy).astype(np.int64), 0, ny)
    j1 = np.clip(np.floor((ys[0] - ymin) / dy).astype(np.int64) + 2, 0, ny)
    nk, nj = np.maximum(k1 - k0, 0), np.maximum(j1 - j0, 0)
    cand = nk * nj

    rows, xcs, ws = [], [], []
    start = 0
    m = len(f)
    while start < m:
        # a batch of triangles with a bounded number of candidate rays
        csum = np.cumsum(cand[start:])
        stop = start + max(1, int(np.searchsorted(csum, _BATCH, side="right")))
        sl = slice(start, stop)
        start = stop
        c = cand[sl]
        if c.sum() == 0:
            continue
        tri = np.repeat(np.arange(sl.start, sl.stop), c)
        local = np.arange(tri.size) - np.repeat(np.cumsum(c) - c, c)
        kk = k0[tri] + local // nj[tri]
        jj = j0[tri] + local % nj[tri]
        py, pz = ys[jj], zs[kk]
        inside = np.ones(tri.size, dtype=bool)
        lam = []
        for e in range(3):
            s, t = f[tri, e], f[tri, (e + 1) % 3]
            lo, hi = np.minimum(s, t), np.maximum(s, t)
            # canonical edge function: the same bits for both faces sharing the edge
            ly, lz = P[lo, 0], P[lo, 1]
            E = (P[hi, 0] - ly) * (pz - lz) - (P[hi, 1] - lz) * (py - ly)
            E = np.where(s == lo, E, -E)
            sg = sigma[tri]
            # tie rule on the edge direction as seen with positive orientation
            dy_e = sg * (P[t, 0] - P[s, 0])
            dz_e = sg * (P[t, 1] - P[s, 1])
            owned = (dz_e < 0) | ((dz_e == 0) & (dy_e > 0))
            inside &= (sg * E > 0) | ((E == 0) & owned)
            lam.append(E)
        if not inside.any():
            continue
        tri, kk, jj = tri[inside], kk[inside], jj[inside]
        # barycentric weights: the edge opposite vertex v is edge (v+1) % 3
        l_p, l_q, l_r = lam[1][inside], lam[2][inside], lam[0][inside]
        tot = l_p + l_q + l_r
        X = vertices[:, 0]
        xc = (l_p * X[f[tri, 0]] + l_q * X[f[tri, 1]] + l_r * X[f[tri, 2]]) / tot
        rows.append(kk * ny + jj)
        xcs.append(xc)
        ws.append((-sigma[tri]).astype(np.int32))  # normal towards -x: the ray enters
    if not rows:
        return np.zeros((nz, ny, nx), dtype=np.int32)
    wind = _accumulate(np.concatenate(rows), np.concatenate(xcs), np.concatenate(ws), nz * ny, x0, dx, nx)
    return wind.reshape(nz, ny, nx)


# -- per-item inside indicator ---------------------------------------------------------
def _inside_box(item, shp, ext, s):
    """Covered fraction of each pixel within the item's bounding box.

    Returns
    -------
    slices : tuple of slice
        Where the box sits in the full grid.
    frac : ndarray
        Covered fraction (float64) if ``s > 1``, else a bool array.
    """
    v = item.vertices
    if len(shp) == 2:
        ny, nx = shp
        xmin, xmax, ymin, ymax = ext
        i0, i1 = _bbox(v[:, 0].min(), v[:, 0].max(), xmin, xmax, nx)
        j0, j1 = _bbox(v[:, 1].min(), v[:, 1].max(), ymin, ymax, ny, flip=True)
        sl = (slice(j0, j1), slice(i0, i1))
        if i1 <= i0 or j1 <= j0:
            return sl, None
        ys = _y_centres(ny * s, ymin, ymax, j0 * s, j1 * s)
        dx = (xmax - xmin) / (nx * s)
        x0 = xmin + (i0 * s + 0.5) * dx
        wind = _winding_polygon(v, ys, x0, dx, (i1 - i0) * s)
    else:
        nz, ny, nx = shp
        xmin, xmax, ymin, ymax, zmin, zmax = ext
        i0, i1 = _bbox(v[:, 0].min(), v[:, 0].max(), xmin, xmax, nx)
        j0, j1 = _bbox(v[:, 1].min(), v[:, 1].max(), ymin, ymax, ny, flip=True)
        k0, k1 = _bbox(v[:, 2].min(), v[:, 2].max(), zmin, zmax, nz)
        sl = (slice(k0, k1), slice(j0, j1), slice(i0, i1))
        if i1 <= i0 or j1 <= j0 or k1 <= k0:
            return sl, None
        ys = _y_centres(ny * s, ymin, ymax, j0 * s, j1 * s)
        zs = _x_centres(nz * s, zmin, zmax, k0 * s, k1 * s)
        dx = (xmax - xmin) / (nx * s)
        x0 = xmin + (i0 * s + 0.5) * dx
        wind = _winding_mesh(v, item.faces, zs, ys, x0, dx, (i1 - i0) * s)
    inside = wind != 0
    if s == 1:
        return sl, inside
    # block average of the s x s (x s) sub-samples
    shape = []
    for n in inside.shape:
        shape += [n // s, s]
    frac = inside.reshape(shape).mean(axis=tuple(range(1, 2 * inside.ndim, 2)))
    return sl, frac


def coverage(item, shape, extent, supersample=1):
    """Fraction of each pixel inside one polygon or mesh.

    Parameters
    ----------
    item : Polygon (2D grid), Mesh (3D grid) or SubdivisionSurface
    shape, extent :
        The grid (see :func:`check_grid`).
    supersample : int
        Sub-samples per pixel and axis; 1 tests the pixel centre only.

    Returns
    -------
    ndarray, shape ``shape``
        float64 in [0, 1] (with ``supersample == 1`` only 0 or 1).
    """
    shp, ext = check_grid(shape, extent)
    s = _supersample(supersample)
    (it,) = _as_items([item], len(shp))
    out = np.zeros(shp, dtype=np.float64)
    sl, frac = _inside_box(it, shp, ext, s)
    if frac is not None:
        out[sl] = frac
    return out


def rasterize(items, shape, extent, supersample=1, dtype=np.float64):
    """Attenuation image of a scene: sum over items of attenuation x covered fraction.

    Parameters
    ----------
    items : Polygon / Mesh / SubdivisionSurface or a sequence of them
        All 2D (Polygon) for a 2D grid or all 3D (Mesh) for a 3D grid.
    shape : (rows, cols) or (slices, rows, cols)
    extent : (xmin, xmax, ymin, ymax[, zmin, zmax])
        mm, see the module docstring for the pixel convention.
    supersample : int
        Sub-samples per pixel and axis (partial-volume effect); 1 tests the
        pixel centres only.
    dtype : numpy dtype
        Output type (float32 for ASTRA).

    Returns
    -------
    ndarray, shape ``shape``
        Attenuation in 1/mm.
    """
    shp, ext = check_grid(shape, extent)
    s = _supersample(supersample)
    items = _as_items(items, len(shp))
    out = np.zeros(shp, dtype=np.float64)
    for it in items:
        sl, frac = _inside_box(it, shp, ext, s)
        if frac is not None:
            out[sl] += it.attenuation * frac
    return out.astype(dtype, copy=False)


def label_image(items, shape, extent):
    """Label image: pixel centres inside ``items[i]`` get ``i + 1``, the rest 0.

    Parameters
    ----------
    items : sequence of Polygon (2D) or Mesh (3D) (or SubdivisionSurface)
    shape, extent :
        The grid (see :func:`check_grid`).

    Returns
    -------
    ndarray of int32, shape ``shape``
        Where items overlap, the later one wins.
    """
    shp, ext = check_grid(shape, extent)
    items = _as_items(items, len(shp))
    out = np.zeros(shp, dtype=np.int32)
    for i, it in enumerate(items):
        sl, inside = _inside_box(it, shp, ext, 1)
        if inside is not None:
            out[sl][inside] = i + 1
    return out


def bubble_mask(items, shape, extent):
    """Boolean mask of the pixel centres inside any of ``items``.

    Parameters
    ----------
    items : Polygon / Mesh / SubdivisionSurface or a sequence of them
    shape, extent :
        The grid (see :func:`check_grid`).

    Returns
    -------
    ndarray of bool, shape ``shape``
    """
    shp, ext = check_grid(shape, extent)
    items = _as_items(items, len(shp))
    out = np.zeros(shp, dtype=bool)
    for it in items:
        sl, inside = _inside_box(it, shp, ext, 1)
        if inside is not None:
            out[sl] |= inside
    return out
