"""The raster backend's compiled kernels (numba), at module level so that numba's disk cache hits.

Kept apart from :mod:`.raster` so that numba is imported only when the
backend is used. Defined at module level rather than in a factory: numba's
cache key hashes a closure's captured variables, and captured dispatchers
serialise differently in every process, so closures were compiled again in
each one (about 2.5 s per process).
See :mod:`bubsub.core.projection.backends.raster` for the method.
"""

from __future__ import annotations

import numba
import numpy as np

from bubsub.core.projection.backends.jit import cached

__all__ = ["raster3d", "raster2d", "stored_face_sums", "pixel_ray_lengths"]

# numpy error model: float division by zero gives inf instead of a checked exception
jit = cached(numba.njit, nogil=True, error_model="numpy")


@jit
def ray_length(p, col, row, cone, S, D, U, V, rows, cols, kc, kr):
    """Source-to-detector length of the ray through lattice point (col, row); 1 for parallel beams.

    ``kc``, ``kr``: lattice points per pixel along the columns and the rows.
    """
    if not cone:
        return 1.0
    a = (col + 0.5) / kc - 0.5 * cols
    b = (row + 0.5) / kr - 0.5 * rows
    e0 = D[p, 0] - S[p, 0] + a * U[p, 0] + b * V[p, 0]
    e1 = D[p, 1] - S[p, 1] + a * U[p, 1] + b * V[p, 1]
    e2 = D[p, 2] - S[p, 2] + a * U[p, 2] + b * V[p, 2]
    return np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)


@jit
def pixel_ray_lengths(S, D, U, V, rows, cols, out):
    """``out[p * rows * cols + r * cols + c]``: the ray length (:func:`ray_length`) of every pixel centre."""
    for p in range(S.shape[0]):
        for r in range(rows):
            for c in range(cols):
                out[(p * rows + r) * cols + c] = ray_length(p, c, r, True, S, D, U, V, rows, cols, 1, 1)


@jit
def edge_from(ia, ib, xa, ya, xb, yb, sig):
    """An edge as seen from its lower-indexed vertex: base, direction, orientation sign, tie rule.

    ``ia``, ``ib``: the vertices' indices; ``(xa, ya)``, ``(xb, yb)``: their lattice coordinates.
    Written with selects rather than branches: the vertex order is random
    from face to face, and mispredicted branches cost more than the
    arithmetic of a triangle that covers one lattice point or none.
    """
    swap = ib < ia
    xl = xb if swap else xa
    yl = yb if swap else ya
    s = -sig if swap else sig
    dx, dy = (xa if swap else xb) - xl, (ya if swap else yb) - yl
    sdx, sdy = s * dx, s * dy
    return xl, yl, dx, dy, s, (sdy < 0.0) | ((sdy == 0.0) & (sdx > 0.0))


@jit
def passes(g, tie):
    """An edge function's verdict: inside, or exactly on the edge and keeping ties (no branches)."""
    return (g > 0.0) | ((g == 0.0) & tie)


@jit
def footprint(X, Y, n_cols, n_rows):
    """Lattice box (c0, c1, r0, r1) covering every projected vertex, clipped to the detector.

    One pass with selects instead of ``X.min()`` and three more: numpy's
    NaN-aware reductions are scalar here, 0.8 ms per projection at 256,000
    vertices. Projected vertices are finite (the projector checks the scene).
    """
    lo_x = hi_x = X[0]
    lo_y = hi_y = Y[0]
    for i in range(X.shape[0]):
        x, y = X[i], Y[i]
        lo_x = x if x < lo_x else lo_x
        hi_x = x if x > hi_x else hi_x
        lo_y = y if y < lo_y else lo_y
        hi_y = y if y > hi_y else hi_y
    c0 = max(int(np.ceil(lo_x)), 0)
    c1 = min(int(np.floor(hi_x)), n_cols - 1)
    r0 = max(int(np.ceil(lo_y)), 0)
    r1 = min(int(np.floor(hi_y)), n_rows - 1)
    return c0, c1, r0, r1


@jit
def crossing(a, cone, lin, num, nU, nr):
    """``(den, value)`` of a face's crossing at detector coordinate ``a``: ``|n.e|`` and ``n.(x0 - S) / |n.e|``
    (cone; times the ray length later), or ``|n.r|`` and ``n.(x0 - P) / |n.r|`` (parallel)."""
    if cone:
        den = abs(lin + a * nU)
        return den, num / den
    return nr, (lin - a * nU) / nr


@jit
def project_all(verts, p, cone, S, D, N, Au, Bv, rows, cols, k, X, Y, iW):
    """Every vertex's lattice coordinates (column ``X``, row ``Y``) in projection p, and ``iW``:
    1 / projective depth (cone; 1 for parallel beams).

    The projection's constants are taken out of the loop: at fine
    subdivision this loop runs over hundreds of thousands of vertices per
    projection.
    """
    sn, au, bv = S[p], Au[p], Bv[p]
    nn, dd = N[p], D[p]
    uc, vr = 0.5 * cols, 0.5 * rows
    if cone:
        # r = S + (h / w) e - D on the detector, e = x - S, w = e.N
        h = (dd[0] - sn[0]) * nn[0] + (dd[1] - sn[1]) * nn[1] + (dd[2] - sn[2]) * nn[2]
        sa = (sn[0] - dd[0]) * au[0] + (sn[1] - dd[1]) * au[1] + (sn[2] - dd[2]) * au[2]
        sb = (sn[0] - dd[0]) * bv[0] + (sn[1] - dd[1]) * bv[1] + (sn[2] - dd[2]) * bv[2]
        for i in range(verts.shape[0]):
            e0, e1, e2 = verts[i, 0] - sn[0], verts[i, 1] - sn[1], verts[i, 2] - sn[2]
            iw = 1.0 / (e0 * nn[0] + e1 * nn[1] + e2 * nn[2])
            lam = h * iw
            X[i] = (sa + lam * (e0 * au[0] + e1 * au[1] + e2 * au[2]) + uc) * k - 0.5
            Y[i] = (sb + lam * (e0 * bv[0] + e1 * bv[1] + e2 * bv[2]) + vr) * k - 0.5
            iW[i] = iw
    else:
        # r = x + m S - D, m = (D - x).N / S.N: along the ray onto the detector plane
        irn = 1.0 / (sn[0] * nn[0] + sn[1] * nn[1] + sn[2] * nn[2])
        dn = dd[0] * nn[0] + dd[1] * nn[1] + dd[2] * nn[2]
        sa = sn[0] * au[0] + sn[1] * au[1] + sn[2] * au[2]
        sb = sn[0] * bv[0] + sn[1] * bv[1] + sn[2] * bv[2]
        da = dd[0] * au[0] + dd[1] * au[1] + dd[2] * au[2]
        db = dd[0] * bv[0] + dd[1] * bv[1] + dd[2] * bv[2]
        for i in range(verts.shape[0]):
            x0, x1, x2 = verts[i, 0], verts[i, 1], verts[i, 2]
            m = (dn - (x0 * nn[0] + x1 * nn[1] + x2 * nn[2])) * irn
            X[i] = (x0 * au[0] + x1 * au[1] + x2 * au[2] - da + m * sa + uc) * k - 0.5
            Y[i] = (x0 * bv[0] + x1 * bv[1] + x2 * bv[2] - db + m * sb + vr) * k - 0.5
            iW[i] = 1.0


@jit
def _min(a, b):
    return a if a < b else b


@jit
def _max(a, b):
    return a if a > b else b


@jit
def lattice_box(x0, x1, x2, y0, y1, y2, F0, F1, R0, R1):
    """The lattice box ``c0..c1, r0..r1`` (as floats) of a triangle's projected vertices, clipped to the
    footprint ``F0..F1, R0..R1``; empty (c0 > c1 or r0 > r1) when it holds no lattice point. Selects,
    not branches, so that :func:`chunk_candidates`' loop over it vectorises."""
    c0 = _max(np.ceil(_min(_min(x0, x1), x2)), F0)
    c1 = _min(np.floor(_max(_max(x0, x1), x2)), F1)
    r0 = _max(np.ceil(_min(_min(y0, y1), y2)), R0)
    r1 = _min(np.floor(_max(_max(y0, y1), y2)), R1)
    return c0, c1, r0, r1


# faces per chunk of the candidate pass: its buffers stay in L1
CHUNK = 256


@jit
def chunk_candidates(faces, s, m, X, Y, F0, F1, R0, R1, buf, keep, idx):
    """Faces ``s .. s + m - 1`` that may hold a lattice point; returns how many, their positions in
    the chunk in ``idx``, and every face's lattice coordinates and box (as floats) in ``buf``:
    rows ``x0 x1 x2 y0 y1 y2 c0 c1 r0 r1``.

    The projected vertices are gathered first, then tested over contiguous
    lanes (LLVM vectorises that loop), then the kept ones are listed, all
    without branches: at fine subdivision most triangles hold no lattice
    point, the gathers of a face's vertices stop vectorisation, and a
    mispredicted branch per triangle would cost more than the test. A
    triangle is dropped when its box (clipped to the footprint ``F0..F1,
    R0..R1``) holds no lattice point, or when it holds one that is outside by
    far more than the rounding of any evaluation of the edge functions; the
    exact test decides the rest.
    """
    for j in range(m):
        f = s + j
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        buf[0, j], buf[1, j], buf[2, j] = X[i0], X[i1], X[i2]
        buf[3, j], buf[4, j], buf[5, j] = Y[i0], Y[i1], Y[i2]
    for j in range(m):
        x0, x1, x2, y0, y1, y2 = buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j]
        c0, c1, r0, r1 = lattice_box(x0, x1, x2, y0, y1, y2, F0, F1, R0, R1)
        area2 = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
        t = abs(x0) + abs(x1) + abs(x2) + abs(y0) + abs(y1) + abs(y2)
        e0 = ((x1 - x0) * (r0 - y0) - (y1 - y0) * (c0 - x0)) * area2
        e1 = ((x2 - x1) * (r0 - y1) - (y2 - y1) * (c0 - x1)) * area2
        e2 = ((x0 - x2) * (r0 - y2) - (y0 - y2) * (c0 - x2)) * area2
        a = abs(area2) * (1e-12 * t * t)
        single = (c0 == c1) & (r0 == r1)
        outside = single & ((e0 < -a) | (e1 < -a) | (e2 < -a))
        keep[j] = (c0 <= c1) & (r0 <= r1) & (area2 != 0.0) & ~outside
        buf[6, j], buf[7, j], buf[8, j], buf[9, j] = c0, c1, r0, r1
    n = 0
    for j in range(m):
        idx[n] = j
        n += keep[j]
    return n


@jit
def face_into(faces, f, X, Y, F0, F1, R0, R1, buf):
    """One face's lattice coordinates and clipped box into ``buf[:, 0]`` (the layout of
    :func:`chunk_candidates`)."""
    i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
    x0, x1, x2, y0, y1, y2 = X[i0], X[i1], X[i2], Y[i0], Y[i1], Y[i2]
    buf[0, 0], buf[1, 0], buf[2, 0], buf[3, 0], buf[4, 0], buf[5, 0] = x0, x1, x2, y0, y1, y2
    buf[6, 0], buf[7, 0], buf[8, 0], buf[9, 0] = lattice_box(x0, x1, x2, y0, y1, y2, F0, F1, R0, R1)


@jit
def faces_pass(p, fa, fb, cand, n_cand, faces, nrm, offset, fmu, S, D, U, V, cone, rows, cols, k, X, Y, iW,
               fc0, fc1, fr0, fr1, L, grad, acc, hit, st_face, st_pix, st_coef, stored, rl, pix_rl, buf, keep, idx):
    """Rasterise faces ``fa..fb - 1`` (in the gradient pass: the ``n_cand`` faces in ``cand``) in
    projection p, within the lattice box ``fc0..fc1, fr0..fr1``, into the lattice array ``L``
    (:func:`raster3d`); returns (crossings, stored)."""
    count = 0
    cap = st_face.shape[0]
    npix = rows * cols
    ik = 1.0 / k
    a_off, b_off = 0.5 * ik - 0.5 * cols, 0.5 * ik - 0.5 * rows  # detector coordinates of lattice point 0
    F0, F1, R0, R1 = float(fc0), float(fc1), float(fr0), float(fr1)
    for block in range(n_cand if grad else (fb - fa + CHUNK - 1) // CHUNK):
        if grad:  # a block of one face
            s = cand[block]
            face_into(faces, s, X, Y, F0, F1, R0, R1, buf)
            n_keep = 1
            idx[0] = 0
        else:
            s = fa + block * CHUNK
            n_keep = chunk_candidates(faces, s, min(CHUNK, fb - s), X, Y, F0, F1, R0, R1, buf, keep, idx)
        for q in range(n_keep):
            j = idx[q]
            f = s + j
            i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
            x0, x1, x2, y0, y1, y2 = buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j]
            c0, c1, r0, r1 = int(buf[6, j]), int(buf[7, j]), int(buf[8, j]), int(buf[9, j])
            area2 = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
            if area2 == 0.0:
                continue  # seen edge-on: no ray crosses it in a single point
            sig = 1.0 if area2 > 0 else -1.0
            bx0, by0, dx0, dy0, s0, t0 = edge_from(i0, i1, x0, y0, x1, y1, sig)
            bx1, by1, dx1, dy1, s1, t1 = edge_from(i1, i2, x1, y1, x2, y2, sig)
            bx2, by2, dx2, dy2, s2, t2 = edge_from(i2, i0, x2, y2, x0, y0, sig)
            # the face's plane terms wait for its first lattice point: at fine
            # subdivision most triangles whose box holds a point hold none
            ready = False
            nU = nV = num = nDS = nr = mu = 0.0
            sum0 = sum1 = sum2 = 0.0
            for row in range(r0, r1 + 1):
                h0, h1, h2 = dx0 * (row - by0), dx1 * (row - by1), dx2 * (row - by2)
                lin = 0.0
                seen = False
                for col in range(c0, c1 + 1):
                    # the same operations for both triangles of an edge: the same number
                    g0 = s0 * (h0 - dy0 * (col - bx0))
                    g1 = s1 * (h1 - dy1 * (col - bx1))
                    g2 = s2 * (h2 - dy2 * (col - bx2))
                    if not (passes(g0, t0) & passes(g1, t1) & passes(g2, t2)):
                        if seen:
                            break  # each edge test is monotonic along a row: the span is over
                        continue
                    if not seen:
                        seen = True
                        if not ready:
                            ready = True
                            n0, n1, n2 = nrm[f, 0], nrm[f, 1], nrm[f, 2]
                            nU = n0 * U[p, 0] + n1 * U[p, 1] + n2 * U[p, 2]
                            nV = n0 * V[p, 0] + n1 * V[p, 1] + n2 * V[p, 2]
                            mu = fmu[f]
                            if cone:
                                # t = n.(x0 - S) |e| / |n.e| along e = D - S + a U + b V
                                num = offset[f] - (n0 * S[p, 0] + n1 * S[p, 1] + n2 * S[p, 2])
                                nDS = n0 * (D[p, 0] - S[p, 0]) + n1 * (D[p, 1] - S[p, 1]) + n2 * (D[p, 2] - S[p, 2])
                            else:
                                # t = n.(x0 - P) / |n.r| from the pixel point P = D + a U + b V
                                num = offset[f] - (n0 * D[p, 0] + n1 * D[p, 1] + n2 * D[p, 2])
                                nr = abs(n0 * S[p, 0] + n1 * S[p, 1] + n2 * S[p, 2])
                            if not grad:
                                hit[p, f >> 3] |= np.uint8(1 << (f & 7))
                        b = row * ik + b_off
                        lin = nDS + b * nV if cone else num - b * nV
                    den, val = crossing(col * ik + a_off, cone, lin, num, nU, nr)
                    if den == 0.0:
                        continue
                    count += 1
                    if not grad:
                        L[row, col] += mu * val
                        if stored >= 0:
                            if stored < cap:
                                # this crossing's coefficients in the gradient pass, for stored_face_sums
                                l0, l1, l2 = g1 * iW[i0], g2 * iW[i1], g0 * iW[i2]
                                c = mu / (den * (l0 + l1 + l2))
                                if not pix_rl:
                                    c *= ray_length(p, col, row, cone, S, D, U, V, rows, cols, k, k)
                                st_face[stored] = f
                                st_pix[stored] = p * npix + (row // k) * cols + col // k
                                st_coef[stored, 0] = c * l0
                                st_coef[stored, 1] = c * l1
                                st_coef[stored, 2] = c * l2
                                stored += 1
                            else:
                                stored = -1
                        continue
                    w = L[row, col]
                    if w == 0.0:
                        continue
                    # barycentric weight of a vertex: the opposite edge's function over its depth
                    l0, l1, l2 = g1 * iW[i0], g2 * iW[i1], g0 * iW[i2]
                    scale = w * mu / (den * (l0 + l1 + l2))
                    sum0 += scale * l0
                    sum1 += scale * l1
                    sum2 += scale * l2
            if grad:
                acc[f, 0] += sum0
                acc[f, 1] += sum1
                acc[f, 2] += sum2
    return count, stored


@jit
def project_range(verts, v0, v1, p, cone, S, D, N, Au, Bv, rows, cols, k, X, Y, iW):
    """:func:`project_all` for vertices ``v0..v1 - 1`` only; returns their :func:`footprint`."""
    project_all(verts[v0:v1], p, cone, S, D, N, Au, Bv, rows, cols, k, X[v0:v1], Y[v0:v1], iW[v0:v1])
    return footprint(X[v0:v1], Y[v0:v1], cols * k, rows * k)


@jit
def raster3d(p0, p1, verts, faces, nrm, offset, fmu, S, D, U, V, N, Au, Bv, cone, rows, cols, k,
             values, weights, acc, grad, hit, st_face, st_pix, st_coef, rl, pix_rl, item_v, item_f, by_item):
    """Forward pass (``grad`` False: ``values``, ``hit``) or gradient pass (``weights`` into ``acc``)
    over projections ``p0..p1``. The forward pass also stores each crossing's face, pixel and
    gradient coefficients while ``st_face`` has room; returns (crossings, stored), with stored
    -1 when the store overflowed or was not asked for (the gradient pass then rasterises again).

    ``pix_rl``: ``rl`` holds every pixel's ray length (:func:`pixel_ray_lengths`; cone beams without
    supersampling), used instead of a square root per crossing, and the stored coefficients leave it
    out (:func:`stored_face_sums` puts it back per pixel).

    ``item_v``, ``item_f`` (n_items + 1,): each item's first vertex and first face (an item's
    faces use only its own vertices). With ``by_item``, a forward pass without supersampling goes item by item,
    each through every projection of the group, and sums straight into ``values``: an item's
    vertices, faces and normals (about 300 kB at 5,120 triangles) then stay in the core's cache
    across the projections, where projection by projection the whole scene (about 50 MB at
    512,000 triangles) came from memory once per projection, over a bus the threads share. Each
    pixel and each face gets its crossings in the same order either way, so the results are the
    same to the bit."""
    nv, nf = verts.shape[0], faces.shape[0]
    X, Y, iW = np.empty(nv), np.empty(nv), np.empty(nv)
    cand = np.empty(nf, np.int64)
    buf, keep, idx = np.empty((10, CHUNK)), np.empty(CHUNK, np.bool_), np.empty(CHUNK, np.int64)
    C, R = cols * k, rows * k
    npix = rows * cols
    count = 0
    stored = 0 if not grad and st_face.shape[0] > 0 else -1
    if by_item and not grad and k == 1:
        for it in range(item_v.shape[0] - 1):
            for p in range(p0, p1):
                fc0, fc1, fr0, fr1 = project_range(verts, item_v[it], item_v[it + 1], p, cone, S, D, N, Au, Bv,
                                                   rows, cols, k, X, Y, iW)
                if fc0 > fc1 or fr0 > fr1:
                    continue
                c, stored = faces_pass(p, item_f[it], item_f[it + 1], cand, 0, faces, nrm, offset, fmu, S, D, U, V,
                                       cone, rows, cols, k, X, Y, iW, fc0, fc1, fr0, fr1,
                                       values[p * npix:(p + 1) * npix].reshape((rows, cols)), grad, acc, hit,
                                       st_face, st_pix, st_coef, stored, rl, pix_rl, buf, keep, idx)
                count += c
        # the lattice sums times the ray length (the projection-major path adds L * length to a zero)
        for pix in range(p0 * npix, p1 * npix):
            if values[pix] != 0.0:
                values[pix] *= rl[pix] if pix_rl else ray_length(
                    pix // npix, pix % cols, (pix % npix) // cols, cone, S, D, U, V, rows, cols, 1, 1)
        return count, stored
    L = np.zeros((R, C))  # per lattice point: sum of mu t / |e| (forward) or w |e| (gradient)
    for p in range(p0, p1):
        project_all(verts, p, cone, S, D, N, Au, Bv, rows, cols, k, X, Y, iW)
        fc0, fc1, fr0, fr1 = footprint(X, Y, C, R)
        if fc0 > fc1 or fr0 > fr1:
            continue
        for row in range(fr0, fr1 + 1):
            for col in range(fc0, fc1 + 1):
                if grad:
                    pix = p * npix + (row // k) * cols + col // k
                    L[row, col] = weights[pix] * (rl[pix] if pix_rl else ray_length(
                        p, col, row, cone, S, D, U, V, rows, cols, k, k))
                else:
                    L[row, col] = 0.0
        n_cand = 0
        if grad:  # only the faces on which the forward pass found a crossing
            for byte in range(hit.shape[1]):
                bits = hit[p, byte]
                if bits == 0:
                    continue
                for t in range(8):
                    cand[n_cand] = byte * 8 + t
                    n_cand += (bits >> t) & 1
        c, stored = faces_pass(p, 0, nf, cand, n_cand, faces, nrm, offset, fmu, S, D, U, V, cone, rows, cols, k,
                               X, Y, iW, fc0, fc1, fr0, fr1, L, grad, acc, hit, st_face, st_pix, st_coef, stored,
                               rl, pix_rl, buf, keep, idx)
        count += c
        if not grad:
            for row in range(fr0, fr1 + 1):
                for col in range(fc0, fc1 + 1):
                    if L[row, col] != 0.0:
                        pix = p * npix + (row // k) * cols + col // k
                        values[pix] += L[row, col] * (rl[pix] if pix_rl else ray_length(
                            p, col, row, cone, S, D, U, V, rows, cols, k, k))
    return count, stored


@jit
def raster2d(p0, p1, verts, segs, nrm, offset, fmu, S, D, U, V, N, Au, Bv, cone, rows, cols, k,
             values, weights, acc, grad):
    nv, ns = verts.shape[0], segs.shape[0]
    X, Y, iW = np.empty(nv), np.empty(nv), np.empty(nv)
    C = cols * k
    L = np.zeros(C)
    count = 0
    for p in range(p0, p1):
        project_all(verts, p, cone, S, D, N, Au, Bv, rows, cols, k, X, Y, iW)
        fc0, fc1, _, _ = footprint(X, X, C, C)
        if fc0 > fc1:
            continue
        for col in range(fc0, fc1 + 1):
            L[col] = weights[p * cols + col // k] * ray_length(p, col, 0, cone, S, D, U, V, 1, cols, k, 1) if grad else 0.0
        for f in range(ns):
            i0, i1 = segs[f, 0], segs[f, 1]
            lo, hi = min(X[i0], X[i1]), max(X[i0], X[i1])
            c0 = max(int(np.ceil(lo)), fc0)
            c1 = min(int(np.ceil(hi)) - 1, fc1)  # [lo, hi): the last point below hi
            if c0 > c1:
                continue
            n0, n1 = nrm[f, 0], nrm[f, 1]
            nU = n0 * U[p, 0] + n1 * U[p, 1]
            mu = fmu[f]
            if cone:
                num = offset[f] - (n0 * S[p, 0] + n1 * S[p, 1])
                lin = n0 * (D[p, 0] - S[p, 0]) + n1 * (D[p, 1] - S[p, 1])
                nr = 0.0
            else:
                num = offset[f] - (n0 * D[p, 0] + n1 * D[p, 1])
                lin = num
                nr = abs(n0 * S[p, 0] + n1 * S[p, 1])
                if nr == 0.0:
                    continue
            for col in range(c0, c1 + 1):
                den, val = crossing((col + 0.5) / k - 0.5 * cols, cone, lin, num, nU, nr)
                if den == 0.0:
                    continue
                count += 1
                if not grad:
                    L[col] += mu * val
                    continue
                w = L[col]
                if w == 0.0:
                    continue
                t = (col - X[i0]) / (X[i1] - X[i0])
                l0, l1 = (1.0 - t) * iW[i0], t * iW[i1]
                scale = w * mu / (den * (l0 + l1))
                acc[f, 0] += scale * l0
                acc[f, 1] += scale * l1
        if not grad:
            for col in range(fc0, fc1 + 1):
                if L[col] != 0.0:
                    values[p * cols + col // k] += L[col] * ray_length(p, col, 0, cone, S, D, U, V, 1, cols, k, 1)
    return count


@jit
def stored_face_sums(st_face, st_pix, st_coef, n, weights, acc, rl, pix_rl):
    """``acc[f, j] += weights[pixel] * coef_j`` over the first ``n`` stored crossings (times the pixel's
    ray length ``rl[pixel]`` when ``pix_rl``: see :func:`raster3d`)."""
    for i in range(n):
        w = weights[st_pix[i]]
        if pix_rl:
            w *= rl[st_pix[i]]
        if w != 0.0:
            f = st_face[i]
            acc[f, 0] += w * st_coef[i, 0]
            acc[f, 1] += w * st_coef[i, 1]
            acc[f, 2] += w * st_coef[i, 2]
