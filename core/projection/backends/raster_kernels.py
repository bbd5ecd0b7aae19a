"""The raster backend's compiled kernels (numba), at module level so that numba's disk cache hits.

Kept apart from :mod:`.raster` so that numba is imported only when the
backend is used. Defined at module level rather than in a factory: numba's
cache key hashes a closure's captured variables, and captured dispatchers
serialise differently in every process, so closures would be compiled again
in each one (seconds per process).

One module on purpose: numba's cache checks only the source file of the
function it compiled, not of the compiled functions it calls, so a kernel
calling into another module could keep running stale machine code after
that module changed. See :mod:`bubsub.core.projection.backends.raster` for
the method.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from bubsub.core.projection.backends.jit import cached

__all__ = ["raster3d", "raster2d", "stored_face_sums", "item_face_sums", "pixel_ray_lengths", "stopped"]

# numpy error model: float division by zero gives inf instead of a checked exception
jit = cached(numba.njit, nogil=True, error_model="numpy")

# stored crossings (stored_face_sums) and 2D segments (raster2d) between two reads of the stop flag;
# the 3D passes read it per view, per chunk of CHUNK faces and per row of a large box
STOP_EVERY = 1 << 14


@intrinsic
def stopped(typingctx, flag):
    """Whether the stop flag ``flag`` ((1,) uint8, :func:`~bubsub.core.projection.backends.base.stop_flag`)
    is set. An atomic (monotonic) load: the compiler reads the byte afresh at every call, where a plain
    ``flag[0]`` could be read once before a loop and never see the watchdog thread set it. On x86 and
    ARM it is an ordinary load."""
    if not (isinstance(flag, types.Array) and flag.dtype == types.uint8):
        return None

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        value = builder.load_atomic(data, "monotonic", 1)
        return builder.icmp_unsigned("!=", value, ir.Constant(value.type, 0))

    return types.boolean(flag), codegen


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
def pixel_ray_lengths(S, D, U, V, rows, cols, out, stop):
    """``out[p * rows * cols + r * cols + c]``: the ray length (:func:`ray_length`) of every pixel centre
    (unfinished once ``stop`` is set: see :func:`stopped`)."""
    for p in range(S.shape[0]):
        if stopped(stop):
            return
        for r in range(rows):
            for c in range(cols):
                out[(p * rows + r) * cols + c] = ray_length(p, c, r, True, S, D, U, V, rows, cols, 1, 1)


@jit
def edge_from(swap, xa, ya, xb, yb, sig):
    """An edge as seen from its lower-indexed vertex: base, direction, orientation sign, tie rule.

    ``swap``: whether the edge's second vertex has the lower index (``ib < ia``);
    ``(xa, ya)``, ``(xb, yb)``: the vertices' lattice coordinates.
    Written with selects rather than branches: the vertex order is random
    from face to face, and mispredicted branches cost more than the
    arithmetic of a triangle that covers one lattice point or none.
    """
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
def footprint(XY, n_cols, n_rows):
    """Lattice box (c0, c1, r0, r1) covering every projected vertex (``XY`` (n, 2): column, row),
    clipped to the detector.

    One pass with selects instead of ``X.min()`` and three more: numpy's
    NaN-aware reductions are scalar here, 0.8 ms per projection at 256,000
    vertices. Projected vertices are finite (the projector checks the scene).
    """
    lo_x = hi_x = XY[0, 0]
    lo_y = hi_y = XY[0, 1]
    for i in range(XY.shape[0]):
        x, y = XY[i, 0], XY[i, 1]
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
def project_all(verts, p, cone, S, D, N, Au, Bv, rows, cols, k, XY, iW):
    """Every vertex's lattice coordinates (``XY[i]``: column, row) in projection p, and ``iW``:
    1 / projective depth (cone; 1 for parallel beams).

    Column and row side by side: the candidate pass reads both for each corner
    of each face, in random order, and one cache line then serves both (level
    3 forward, one thread: 4-11 ms less than two arrays, paired).

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
            XY[i, 0] = (sa + lam * (e0 * au[0] + e1 * au[1] + e2 * au[2]) + uc) * k - 0.5
            XY[i, 1] = (sb + lam * (e0 * bv[0] + e1 * bv[1] + e2 * bv[2]) + vr) * k - 0.5
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
            XY[i, 0] = (x0 * au[0] + x1 * au[1] + x2 * au[2] - da + m * sa + uc) * k - 0.5
            XY[i, 1] = (x0 * bv[0] + x1 * bv[1] + x2 * bv[2] - db + m * sb + vr) * k - 0.5
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


# faces per chunk of the candidate pass: its buffer stays in the core's first caches
CHUNK = 256

# The rows of a chunk's flat buffer ``w`` (chunk_buffers), CHUNK values each: row r of lane j is
# ``w[r * CHUNK + j]``. Constant offsets into one array let LLVM vectorise loops over it without
# run-time checks that the rows do not overlap (with a 2D array's strides it gives up: "too many
# memory checks"). Numba compiles these module constants into the kernels.
#
# One lane per face of the chunk (chunk_candidates, face_into):
VX0, VX1, VX2, VY0, VY1, VY2 = 0, 1, 2, 3, 4, 5  # the projected vertices' lattice coordinates
BOX = 6  # first row of the face's lattice box clipped to the footprint, c0 c1 r0 r1:
BOX_C0, BOX_C1, BOX_R0, BOX_R1 = BOX, BOX + 1, BOX + 2, BOX + 3
# One lane per small candidate, rows SMALL + r (gather_small writes them, small_terms reads them):
SMALL = 10
S_ORDER = 10  # the vertex indices' order: edge_from's three swaps as bits (after the coordinates, r 0-5)
S_NORMAL = 13  # the face's unit normal (3 rows)
S_OFFSET = 16  # its plane offset n.x0
S_DEPTH = 17  # its vertices' inverse depths (3 rows)
# small_terms' results for lattice point k (0-3) of the box, rows SMALL + POINT_ROWS * k + P_*, over
# rows already read (point 0 over the coordinates, point 1 over S_ORDER .. S_OFFSET - 1):
POINT_ROWS = 10
P_VALUE, P_COEF, P_LATTICE, P_FLAG = 0, 1, 4, 5  # value, three gradient coefficients, lattice index, crossing
SMALL_ROWS = 3 * POINT_ROWS + P_FLAG + 1  # through point 3's flag


@jit
def chunk_candidates(faces, s, m, XY, F0, F1, R0, R1, w, flags, idx, sidx):
    """Faces ``s .. s + m - 1`` that may hold a lattice point, in two lists: those whose box holds
    at most two (``sidx``: small) and the others (``idx``); returns how many of each, and every
    face's lattice coordinates and box (as floats) in rows :data:`VX0` .. :data:`BOX_R1` of ``w``.

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
        w[VX0 * CHUNK + j], w[VX1 * CHUNK + j], w[VX2 * CHUNK + j] = XY[i0, 0], XY[i1, 0], XY[i2, 0]
        w[VY0 * CHUNK + j], w[VY1 * CHUNK + j], w[VY2 * CHUNK + j] = XY[i0, 1], XY[i1, 1], XY[i2, 1]
    for j in range(m):
        x0, x1, x2 = w[VX0 * CHUNK + j], w[VX1 * CHUNK + j], w[VX2 * CHUNK + j]
        y0, y1, y2 = w[VY0 * CHUNK + j], w[VY1 * CHUNK + j], w[VY2 * CHUNK + j]
        c0, c1, r0, r1 = lattice_box(x0, x1, x2, y0, y1, y2, F0, F1, R0, R1)
        area2 = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
        t = abs(x0) + abs(x1) + abs(x2) + abs(y0) + abs(y1) + abs(y2)
        e0 = ((x1 - x0) * (r0 - y0) - (y1 - y0) * (c0 - x0)) * area2
        e1 = ((x2 - x1) * (r0 - y1) - (y2 - y1) * (c0 - x1)) * area2
        e2 = ((x0 - x2) * (r0 - y2) - (y0 - y2) * (c0 - x2)) * area2
        a = abs(area2) * (1e-12 * t * t)
        single = (c0 == c1) & (r0 == r1)
        outside = single & ((e0 < -a) | (e1 < -a) | (e2 < -a))
        flags[j] = (c0 <= c1) & (r0 <= r1) & (area2 != 0.0) & ~outside
        flags[CHUNK + j] = (c1 - c0) + (r1 - r0) <= 1.0
        w[BOX_C0 * CHUNK + j], w[BOX_C1 * CHUNK + j] = c0, c1
        w[BOX_R0 * CHUNK + j], w[BOX_R1 * CHUNK + j] = r0, r1
    n = n_small = 0
    for j in range(m):
        idx[n] = j
        sidx[n_small] = j
        n += flags[j] & ~flags[CHUNK + j]
        n_small += flags[j] & flags[CHUNK + j]
    return n, n_small


@jit
def face_into(faces, f, XY, F0, F1, R0, R1, w):
    """One face's lattice coordinates and clipped box into lane 0 of rows :data:`VX0` ..
    :data:`BOX_R1` of ``w`` (the layout of :func:`chunk_candidates`)."""
    i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
    x0, x1, x2, y0, y1, y2 = XY[i0, 0], XY[i1, 0], XY[i2, 0], XY[i0, 1], XY[i1, 1], XY[i2, 1]
    for r, v in enumerate((x0, x1, x2, y0, y1, y2) + lattice_box(x0, x1, x2, y0, y1, y2, F0, F1, R0, R1)):
        w[r * CHUNK] = v


@jit
def projection_terms(p, cone, S, D, U, V):
    """Projection p's constants of :func:`plane_terms`: U, V, the ray's reference point (the source
    for cone beams, the detector's centre for parallel ones), D - S and S."""
    q = (S[p, 0], S[p, 1], S[p, 2]) if cone else (D[p, 0], D[p, 1], D[p, 2])
    return (U[p, 0], U[p, 1], U[p, 2], V[p, 0], V[p, 1], V[p, 2]) + q + (
        D[p, 0] - S[p, 0], D[p, 1] - S[p, 1], D[p, 2] - S[p, 2], S[p, 0], S[p, 1], S[p, 2])


@jit
def plane_terms(n0, n1, n2, off, pc):
    """A face's plane (unit normal n, offset n.x0) in a projection (:func:`projection_terms`):
    ``(nU, nV, num, nDS, nr)`` for :func:`crossing` (``nDS`` matters for cone beams, ``nr`` for
    parallel beams only).

    Cone: t = n.(x0 - S) |e| / |n.e| along e = D - S + a U + b V; parallel:
    t = n.(x0 - P) / |n.r| from the pixel point P = D + a U + b V.
    """
    nU = n0 * pc[0] + n1 * pc[1] + n2 * pc[2]
    nV = n0 * pc[3] + n1 * pc[4] + n2 * pc[5]
    num = off - (n0 * pc[6] + n1 * pc[7] + n2 * pc[8])
    nDS = n0 * pc[9] + n1 * pc[10] + n2 * pc[11]
    return nU, nV, num, nDS, abs(n0 * pc[12] + n1 * pc[13] + n2 * pc[14])


@jit
def point_forward(col, row, g0, g1, g2, t0, t1, t2, cone, ik, a_off, b_off, nU, nV, num, nDS, nr, mu):
    """A lattice point's crossing, given its three edge functions: (crossing: inside and not
    parallel to the plane, mu times the crossing's value (0 unless a crossing), ``|n.e|`` or
    ``|n.r|`` for :func:`point_coefficients`). Scalars only, without branches, so that it
    inlines and vectorises."""
    b = row * ik + b_off
    den, val = crossing(col * ik + a_off, cone, nDS + b * nV if cone else num - b * nV, num, nU, nr)
    ok = passes(g0, t0) & passes(g1, t1) & passes(g2, t2) & (den != 0.0)
    return ok, mu * val if ok else 0.0, den


@jit
def point_coefficients(g0, g1, g2, w0, w1, w2, mu, den):
    """A crossing's gradient coefficient and its three unnormalised 3D barycentric weights (the
    opposite edge's function over the vertex's depth): ``mu b_j / |n.d|`` is their product over
    their sum."""
    l0, l1, l2 = g1 * w0, g2 * w1, g0 * w2
    return mu / (den * (l0 + l1 + l2)), l0, l1, l2


@jit
def edge_value(bx, by, dx, dy, s, col, row):
    """An edge's function at lattice point (col, row): the same operations for both triangles of
    the edge (:func:`edge_from`), so the same number."""
    return s * (dx * (row - by) - dy * (col - bx))


@jit
def gather_small(faces, s, sidx, n, nrm, offset, iW, w):
    """Copy the small candidates ``sidx[:n]`` of the chunk at face ``s`` into contiguous rows
    ``SMALL ..`` of ``w``: lattice coordinates (``SMALL + VX0 .. VY2``), the vertex indices' order
    (:data:`S_ORDER`), normal and plane offset (:data:`S_NORMAL`, :data:`S_OFFSET`) and the
    vertices' inverse depths (:data:`S_DEPTH`), for :func:`small_terms`. Not the box: computing it again
    there, vectorised, costs less than copying it (level 3 forward, one thread: 6 ms less)."""
    for q in range(n):
        j = sidx[q]
        f = s + j
        # written out rather than as a loop over the rows, which LLVM does not unroll (the loop
        # copies ten rows about 10 % slower at level 3)
        a0, a1, a2 = w[VX0 * CHUNK + j], w[VX1 * CHUNK + j], w[VX2 * CHUNK + j]
        a3, a4, a5 = w[VY0 * CHUNK + j], w[VY1 * CHUNK + j], w[VY2 * CHUNK + j]
        w[(SMALL + VX0) * CHUNK + q], w[(SMALL + VX1) * CHUNK + q], w[(SMALL + VX2) * CHUNK + q] = a0, a1, a2
        w[(SMALL + VY0) * CHUNK + q], w[(SMALL + VY1) * CHUNK + q], w[(SMALL + VY2) * CHUNK + q] = a3, a4, a5
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        w[(SMALL + S_ORDER) * CHUNK + q] = (i1 < i0) + 2 * (i2 < i1) + 4 * (i0 < i2)  # edge_from's swaps
        w[(SMALL + S_NORMAL) * CHUNK + q], w[(SMALL + S_NORMAL + 1) * CHUNK + q] = nrm[f, 0], nrm[f, 1]
        w[(SMALL + S_NORMAL + 2) * CHUNK + q], w[(SMALL + S_OFFSET) * CHUNK + q] = nrm[f, 2], offset[f]
        w[(SMALL + S_DEPTH) * CHUNK + q] = iW[i0]
        w[(SMALL + S_DEPTH + 1) * CHUNK + q], w[(SMALL + S_DEPTH + 2) * CHUNK + q] = iW[i1], iW[i2]


@jit
def point_terms(col, row, edges, w0, w1, w2, cone, ik, a_off, b_off, plane, mu, C):
    """A small candidate's lattice point (col, row): (crossing, value, the three gradient
    coefficients, lattice index ``row * C + col``). ``edges``: the three :func:`edge_from` of the
    face; ``plane``: its :func:`plane_terms`. Scalars only, so that it inlines and vectorises."""
    bx0, by0, dx0, dy0, s0, t0, bx1, by1, dx1, dy1, s1, t1, bx2, by2, dx2, dy2, s2, t2 = edges
    nU, nV, num, nDS, nr = plane
    g0 = edge_value(bx0, by0, dx0, dy0, s0, col, row)
    g1 = edge_value(bx1, by1, dx1, dy1, s1, col, row)
    g2 = edge_value(bx2, by2, dx2, dy2, s2, col, row)
    ok, v, den = point_forward(col, row, g0, g1, g2, t0, t1, t2, cone, ik, a_off, b_off, nU, nV, num, nDS, nr, mu)
    c, l0, l1, l2 = point_coefficients(g0, g1, g2, w0, w1, w2, mu, den)
    return ok, v, c * l0, c * l1, c * l2, row * C + col


@jit
def small_terms(n, w, mu, pc, cone, ik, a_off, b_off, C, F0, F1, R0, R1, quad, cross):
    """The forward terms of the lattice points of the ``n`` small candidates in rows ``SMALL ..`` of
    ``w`` (:func:`gather_small`; attenuation ``mu``): boxes of one or two points, or with ``quad``
    boxes of 2 x 2. Each point gets its :func:`point_terms` (value, three coefficients, lattice
    index as a float, exact) and its crossing flag in rows ``SMALL + POINT_ROWS * k + P_VALUE ..
    P_FLAG``, over rows already read: k = 0 for (c0, r0), 1 for (c1, r1) (never a
    crossing in a one-point box), and for 2 x 2 boxes 2 for (c1, r0) and 3 for (c0, r1). Returns
    how many points are crossings, listed in ``cross`` as 4 times the candidate plus k, each box's
    row by row (the order in which the gradient pass would visit them). ``F0..F1, R0..R1``: the
    bounds the candidate pass clipped the boxes to (:func:`lattice_box`), which this computes again.

    The terms come from one loop without branches over contiguous lanes, which
    LLVM vectorises: at fine subdivision most candidates are such triangles,
    and one by one their set-up (edges, plane, depths) and branches cost more
    than the rest of the pass. The products and the lattice index are formed
    here rather than per crossing in the scalar loop that adds them (level 3
    forward, one thread: about 9 ms less, paired). ``quad`` must be a literal
    (True or False at the call): numba then compiles one function for each,
    with the other's branch removed. With a run-time flag LLVM keeps the branch
    and vectorises nothing (3x slower), and so it does with the set-up in a
    helper taking ``w``: helpers here take scalars only.
    """
    numba.literally(quad)
    for q in range(n):
        x0, x1, x2 = w[(SMALL + VX0) * CHUNK + q], w[(SMALL + VX1) * CHUNK + q], w[(SMALL + VX2) * CHUNK + q]
        y0, y1, y2 = w[(SMALL + VY0) * CHUNK + q], w[(SMALL + VY1) * CHUNK + q], w[(SMALL + VY2) * CHUNK + q]
        c0, c1, r0, r1 = lattice_box(x0, x1, x2, y0, y1, y2, F0, F1, R0, R1)
        order = int(w[(SMALL + S_ORDER) * CHUNK + q])
        plane = plane_terms(w[(SMALL + S_NORMAL) * CHUNK + q], w[(SMALL + S_NORMAL + 1) * CHUNK + q],
                            w[(SMALL + S_NORMAL + 2) * CHUNK + q], w[(SMALL + S_OFFSET) * CHUNK + q], pc)
        w0 = w[(SMALL + S_DEPTH) * CHUNK + q]
        w1, w2 = w[(SMALL + S_DEPTH + 1) * CHUNK + q], w[(SMALL + S_DEPTH + 2) * CHUNK + q]
        area2 = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
        sig = 1.0 if area2 > 0 else -1.0
        edges = (edge_from((order & 1) != 0, x0, y0, x1, y1, sig) + edge_from((order & 2) != 0, x1, y1, x2, y2, sig)
                 + edge_from((order & 4) != 0, x2, y2, x0, y0, sig))
        # written out point by point rather than looped: LLVM vectorises innermost loops only;
        # o is the first row of point k's results (SMALL + POINT_ROWS * k)
        ok, v, a, b, c, lat = point_terms(c0, r0, edges, w0, w1, w2, cone, ik, a_off, b_off, plane, mu, C)
        o = SMALL
        w[(o + P_VALUE) * CHUNK + q], w[(o + P_COEF) * CHUNK + q], w[(o + P_COEF + 1) * CHUNK + q] = v, a, b
        w[(o + P_COEF + 2) * CHUNK + q], w[(o + P_LATTICE) * CHUNK + q] = c, lat
        w[(o + P_FLAG) * CHUNK + q] = 1.0 if ok else 0.0
        ok, v, a, b, c, lat = point_terms(c1, r1, edges, w0, w1, w2, cone, ik, a_off, b_off, plane, mu, C)
        o = SMALL + POINT_ROWS
        w[(o + P_VALUE) * CHUNK + q], w[(o + P_COEF) * CHUNK + q], w[(o + P_COEF + 1) * CHUNK + q] = v, a, b
        w[(o + P_COEF + 2) * CHUNK + q], w[(o + P_LATTICE) * CHUNK + q] = c, lat
        w[(o + P_FLAG) * CHUNK + q] = 1.0 if ok & ((c1 != c0) | (r1 != r0)) else 0.0
        if quad:  # a 2 x 2 box: its other two corners
            ok, v, a, b, c, lat = point_terms(c1, r0, edges, w0, w1, w2, cone, ik, a_off, b_off, plane, mu, C)
            o = SMALL + 2 * POINT_ROWS
            w[(o + P_VALUE) * CHUNK + q], w[(o + P_COEF) * CHUNK + q], w[(o + P_COEF + 1) * CHUNK + q] = v, a, b
            w[(o + P_COEF + 2) * CHUNK + q], w[(o + P_LATTICE) * CHUNK + q] = c, lat
            w[(o + P_FLAG) * CHUNK + q] = 1.0 if ok else 0.0
            ok, v, a, b, c, lat = point_terms(c0, r1, edges, w0, w1, w2, cone, ik, a_off, b_off, plane, mu, C)
            o = SMALL + 3 * POINT_ROWS
            w[(o + P_VALUE) * CHUNK + q], w[(o + P_COEF) * CHUNK + q], w[(o + P_COEF + 1) * CHUNK + q] = v, a, b
            w[(o + P_COEF + 2) * CHUNK + q], w[(o + P_LATTICE) * CHUNK + q] = c, lat
            w[(o + P_FLAG) * CHUNK + q] = 1.0 if ok else 0.0
    m = 0
    for q in range(n):  # each box's crossings row by row: (c0, r0), (c1, r0), (c0, r1), (c1, r1)
        for j in range(4 if quad else 2):
            k = (0, 2, 3, 1)[j] if quad else j
            cross[m] = 4 * q + k
            m += w[(SMALL + POINT_ROWS * k + P_FLAG) * CHUNK + q] != 0.0
    return m


@jit
def lattice_pixel(p, row, col, rows, cols, k):
    """The flat index of lattice point (col, row)'s pixel in projection p."""
    # k == 1 apart: two integer divisions per crossing cost a tenth of the forward pass
    return (p * rows + row) * cols + col if k == 1 else (p * rows + row // k) * cols + col // k


@jit
def put_crossing(st_face, st_pix, st_coef, stored, ok, f, pix, c, l0, l1, l2):
    """Write a lattice point's face, pixel and gradient coefficients at ``stored`` (room checked by
    the caller) and return the next place: ``stored + 1`` at a crossing, ``stored`` otherwise."""
    st_face[stored] = f
    st_pix[stored] = pix
    st_coef[stored, 0] = c * l0
    st_coef[stored, 1] = c * l1
    st_coef[stored, 2] = c * l2
    return stored + ok


@jit
def mark_stored(st_face, st_pix, n, npix, hit):
    """Mark in ``hit`` the face of each of the first ``n`` stored crossings, and return -1: a group
    whose store fills rasterises again for the gradient, visiting the marked faces, and the
    small triangles' crossings mark their faces only once the store is off (a read-modify-write
    of a byte per crossing, 2-3 ns, for a bitmap that a full store never needs)."""
    for i in range(n):
        f = st_face[i]
        hit[st_pix[i] // npix, f >> 3] |= np.uint8(1 << (f & 7))
    return -1


# lattice points of a triangle's box up to which the forward pass evaluates every one without
# branches (faces_pass); larger boxes skip the points outside. foam3d, one thread, against the
# scanning loop alone: 96 is 17 % faster at level 1 and 4 % on a 4x detector; 24 is slower on
# both, and evaluating every box so is 30 % slower at level 1
BOX_POINTS = 96

# lattice points of a box from which faces_pass reads the stop flag per row of it (a face covering a
# whole supersampled detector is millions of points)
STOP_POINTS = 1 << 14


@jit
def faces_pass(p, fa, fb, cand, n_cand, faces, nrm, offset, fmu, S, D, U, V, cone, rows, cols, k, XY, iW,
               fc0, fc1, fr0, fr1, L, grad, acc, hit, st_face, st_pix, st_coef, stored, rl, pix_rl, bufs, stop):
    """Rasterise faces ``fa..fb - 1`` (in the forward pass one item's faces: a chunk takes its
    attenuation from its first face; in the gradient pass the ``n_cand`` faces in ``cand``) in
    projection p, within the lattice box ``fc0..fc1, fr0..fr1``, into the lattice array ``L``
    (:func:`raster3d`); returns (crossings, stored).

    ``bufs``: :func:`chunk_buffers`. The forward pass takes each chunk's small
    candidates first, then its 2 x 2 boxes (both :func:`small_terms`), then the others, each lattice
    point of a box evaluated without branches and its contributions selected
    by its inside test; boxes of more than :data:`BOX_POINTS` points skip the
    points outside and stop a row at the end of its span (the edge functions
    are monotonic along a row).
    Each face's crossings keep their order (row by row), so face sums do not
    depend on it. A group whose store has no room for a chunk's boxes stops
    storing (``stored`` -1): its gradient pass rasterises again.

    ``stop`` (:func:`stopped`) is read before each chunk of faces (each face in
    the gradient pass) and each row of a box of more than :data:`STOP_POINTS`
    points; once it is set the pass returns what it has.
    """
    w, flags, idx, sidx, qidx, cross = bufs
    count = 0
    cap = st_face.shape[0]
    ik = 1.0 / k
    a_off, b_off = 0.5 * ik - 0.5 * cols, 0.5 * ik - 0.5 * rows  # detector coordinates of lattice point 0
    F0, F1, R0, R1 = float(fc0), float(fc1), float(fr0), float(fr1)
    pc = projection_terms(p, cone, S, D, U, V)
    C, npix = L.shape[1], rows * cols
    Lf = L.reshape(L.size)
    for block in range(n_cand if grad else (fb - fa + CHUNK - 1) // CHUNK):
        if stopped(stop):
            break
        if grad:  # a block of one face
            s = cand[block]
            face_into(faces, s, XY, F0, F1, R0, R1, w)
            n_keep = 1
            idx[0] = 0
        else:
            s = fa + block * CHUNK
            n_keep, n_small = chunk_candidates(faces, s, min(CHUNK, fb - s), XY, F0, F1, R0, R1, w, flags, idx,
                                               sidx)
            mu = fmu[s]  # a chunk is one item's faces (raster3d)
            # the 2 x 2 boxes among the others (at level 2 about 40 % of the candidates) go the small
            # ones' way too, listed apart; idx keeps the rest, compacted in place
            n_quad = n_large = 0
            for q in range(n_keep):
                j = idx[q]
                quad = ((w[BOX_C1 * CHUNK + j] - w[BOX_C0 * CHUNK + j] == 1.0)
                        & (w[BOX_R1 * CHUNK + j] - w[BOX_R0 * CHUNK + j] == 1.0))
                qidx[n_quad] = j
                idx[n_large] = j
                n_quad += quad
                n_large += not quad
            n_keep = n_large
            for quad in (False, True):
                listed, n_listed = (qidx, n_quad) if quad else (sidx, n_small)
                if n_listed == 0:
                    continue
                gather_small(faces, s, listed, n_listed, nrm, offset, iW, w)
                if quad:  # literal flags: small_terms is compiled once for each
                    n_cross = small_terms(n_listed, w, mu, pc, cone, ik, a_off, b_off, float(C), F0, F1, R0, R1, True,
                                          cross)
                else:
                    n_cross = small_terms(n_listed, w, mu, pc, cone, ik, a_off, b_off, float(C), F0, F1, R0, R1,
                                          False, cross)
                count += n_cross
                if stored >= 0 and stored + n_cross > cap:
                    stored = mark_stored(st_face, st_pix, stored, npix, hit)
                for e in range(n_cross):
                    q, pt = cross[e] >> 2, cross[e] & 3
                    f = s + listed[q]
                    o = (SMALL + POINT_ROWS * pt) * CHUNK + q  # the point's results (small_terms)
                    lat = int(w[o + P_LATTICE * CHUNK])
                    Lf[lat] += w[o + P_VALUE * CHUNK]
                    if stored < 0:  # a stored crossing marks its face only if the store fills (mark_stored)
                        hit[p, f >> 3] |= np.uint8(1 << (f & 7))
                    else:
                        pix = p * npix + lat if k == 1 else lattice_pixel(p, lat // C, lat % C, rows, cols, k)
                        c = 1.0 if pix_rl else ray_length(p, lat % C, lat // C, cone, S, D, U, V, rows, cols, k, k)
                        stored = put_crossing(st_face, st_pix, st_coef, stored, True, f, pix, c,
                                              w[o + P_COEF * CHUNK], w[o + (P_COEF + 1) * CHUNK],
                                              w[o + (P_COEF + 2) * CHUNK])
        for q in range(n_keep):
            j = idx[q]
            f = s + j
            i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
            x0, x1, x2 = w[VX0 * CHUNK + j], w[VX1 * CHUNK + j], w[VX2 * CHUNK + j]
            y0, y1, y2 = w[VY0 * CHUNK + j], w[VY1 * CHUNK + j], w[VY2 * CHUNK + j]
            c0, c1 = int(w[BOX_C0 * CHUNK + j]), int(w[BOX_C1 * CHUNK + j])
            r0, r1 = int(w[BOX_R0 * CHUNK + j]), int(w[BOX_R1 * CHUNK + j])
            area2 = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
            if area2 == 0.0:
                continue  # seen edge-on: no ray crosses it in a single point
            sig = 1.0 if area2 > 0 else -1.0
            bx0, by0, dx0, dy0, s0, t0 = edge_from(i1 < i0, x0, y0, x1, y1, sig)
            bx1, by1, dx1, dy1, s1, t1 = edge_from(i2 < i1, x1, y1, x2, y2, sig)
            bx2, by2, dx2, dy2, s2, t2 = edge_from(i0 < i2, x2, y2, x0, y0, sig)
            nU, nV, num, nDS, nr = plane_terms(nrm[f, 0], nrm[f, 1], nrm[f, 2], offset[f], pc)
            mu = fmu[f]
            w0, w1, w2 = iW[i0], iW[i1], iW[i2]
            points = (c1 - c0 + 1) * (r1 - r0 + 1)
            if not grad and stored >= 0 and stored + points > cap:
                stored = mark_stored(st_face, st_pix, stored, npix, hit)
            crossed = False
            sum0 = sum1 = sum2 = 0.0
            # large boxes (and the gradient pass) skip the points outside, instead of evaluating them
            scan = points > BOX_POINTS or grad
            large = points > STOP_POINTS
            for row in range(r0, r1 + 1):
                if large and stopped(stop):
                    break
                seen = False
                for col in range(c0, c1 + 1):
                    g0 = edge_value(bx0, by0, dx0, dy0, s0, col, row)
                    g1 = edge_value(bx1, by1, dx1, dy1, s1, col, row)
                    g2 = edge_value(bx2, by2, dx2, dy2, s2, col, row)
                    if scan:
                        if not (passes(g0, t0) & passes(g1, t1) & passes(g2, t2)):
                            if seen:
                                break  # each edge test is monotonic along a row: the span is over
                            continue
                        seen = True
                        if grad and L[row, col] == 0.0:
                            continue
                    ok, v, den = point_forward(col, row, g0, g1, g2, t0, t1, t2, cone, ik, a_off, b_off, nU, nV,
                                               num, nDS, nr, mu)
                    count += ok
                    if grad:
                        c, l0, l1, l2 = point_coefficients(g0, g1, g2, w0, w1, w2, mu, den)
                        scale = L[row, col] * c if ok else 0.0
                        sum0 += scale * l0
                        sum1 += scale * l1
                        sum2 += scale * l2
                        continue
                    crossed |= ok
                    L[row, col] += v
                    if stored >= 0:
                        # this crossing's coefficients in the gradient pass, for stored_face_sums; written
                        # at every point, kept (stored moves on) at a crossing
                        c, l0, l1, l2 = point_coefficients(g0, g1, g2, w0, w1, w2, mu, den)
                        if not pix_rl:
                            c *= ray_length(p, col, row, cone, S, D, U, V, rows, cols, k, k)
                        stored = put_crossing(st_face, st_pix, st_coef, stored, ok, f,
                                              lattice_pixel(p, row, col, rows, cols, k), c, l0, l1, l2)
            if grad:
                acc[f, 0] += sum0
                acc[f, 1] += sum1
                acc[f, 2] += sum2
            else:
                hit[p, f >> 3] |= np.uint8(crossed) << np.uint8(f & 7)
    return count, stored


@jit
def chunk_buffers():
    """Per-thread scratch of :func:`faces_pass`: a chunk's flat buffer (rows :data:`VX0` ..
    ``SMALL + SMALL_ROWS - 1``, see the constants above :func:`chunk_candidates`), its candidate
    flags (kept, small), its candidate lists (others, small, 2 x 2) and its small candidates'
    crossings (:func:`small_terms`)."""
    return (np.empty((SMALL + SMALL_ROWS) * CHUNK), np.empty(2 * CHUNK, np.bool_), np.empty(CHUNK, np.int64),
            np.empty(CHUNK, np.int64), np.empty(CHUNK, np.int64), np.empty(4 * CHUNK, np.int64))


@jit
def raster3d(p0, p1, verts, faces, nrm, offset, fmu, S, D, U, V, N, Au, Bv, cone, rows, cols, k,
             values, weights, acc, grad, hit, st_face, st_pix, st_coef, rl, pix_rl, item_v, item_f, by_item, st_item,
             stop):
    """Forward pass (``grad`` False: ``values``, ``hit``) or gradient pass (``weights`` into ``acc``)
    over projections ``p0..p1``. The forward pass sets the projections' ``values`` (zeroed here, view
    by view: the first writes to a large fresh array are page faults, and they come between two
    reads of the stop flag). The forward pass also stores each crossing's face, pixel and
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
    same to the bit. ``st_item`` (n_items + 1,): there, where each item's stored crossings begin
    (and where the last ends) in the group's part of the store, so that face sums can be split
    among threads by items (:func:`item_face_sums`).

    ``stop``: the stop flag (:func:`stopped`), read per projection, per row of the lattice footprint
    and within :func:`faces_pass`; once it is set the pass returns what it has (the caller raises the
    deadline's error)."""
    nv, nf = verts.shape[0], faces.shape[0]
    XY, iW = np.empty((nv, 2)), np.empty(nv)
    cand = np.empty(nf + 8, np.int64)  # the listing below writes one place past the last face found
    bufs = chunk_buffers()
    C, R = cols * k, rows * k
    npix = rows * cols
    count = 0
    stored = 0 if not grad and st_face.shape[0] > 0 else -1
    if by_item and not grad and k == 1:
        for p in range(p0, p1):
            if stopped(stop):
                return count, stored
            values[p * npix:(p + 1) * npix] = 0.0
        for it in range(item_v.shape[0] - 1):
            st_item[it] = stored
            v0, v1 = item_v[it], item_v[it + 1]
            for p in range(p0, p1):
                if stopped(stop):
                    return count, stored
                project_all(verts[v0:v1], p, cone, S, D, N, Au, Bv, rows, cols, k, XY[v0:v1], iW[v0:v1])
                # boxes clipped to the detector rather than to the item's footprint: the same boxes
                # (a face's box lies within its item's footprint), without a pass over the item's
                # vertices per projection (level 3 forward, one thread: 6 ms of 170); an item off the
                # detector costs a candidate pass whose boxes all clip to nothing
                c, stored = faces_pass(p, item_f[it], item_f[it + 1], cand, 0, faces, nrm, offset, fmu, S, D, U, V,
                                       cone, rows, cols, k, XY, iW, 0, C - 1, 0, R - 1,
                                       values[p * npix:(p + 1) * npix].reshape((rows, cols)), grad, acc, hit,
                                       st_face, st_pix, st_coef, stored, rl, pix_rl, bufs, stop)
                count += c
        st_item[item_v.shape[0] - 1] = stored
        # the lattice sums times the ray length (the projection-major path adds L * length to a zero)
        if pix_rl:  # one vectorised pass; a zero stays a zero
            for pix in range(p0 * npix, p1 * npix):
                values[pix] *= rl[pix]
        else:
            for pix in range(p0 * npix, p1 * npix):
                if values[pix] != 0.0:
                    values[pix] *= ray_length(pix // npix, pix % cols, (pix % npix) // cols, cone, S, D, U, V, rows,
                                              cols, 1, 1)
        return count, stored
    L = np.zeros((R, C))  # per lattice point: sum of mu t / |e| (forward) or w |e| (gradient)
    for p in range(p0, p1):
        if stopped(stop):
            break
        if not grad:
            values[p * npix:(p + 1) * npix] = 0.0
        project_all(verts, p, cone, S, D, N, Au, Bv, rows, cols, k, XY, iW)
        fc0, fc1, fr0, fr1 = footprint(XY, C, R)
        if fc0 > fc1 or fr0 > fr1:
            continue
        for row in range(fr0, fr1 + 1):
            if stopped(stop):  # a supersampled footprint is millions of lattice points
                break
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
        # the forward pass's chunks start at each item's first face, as item by item: the same sums
        for it in range(1 if grad else item_f.shape[0] - 1):
            fa, fb = (0, nf) if grad else (item_f[it], item_f[it + 1])
            c, stored = faces_pass(p, fa, fb, cand, n_cand, faces, nrm, offset, fmu, S, D, U, V, cone, rows, cols,
                                   k, XY, iW, fc0, fc1, fr0, fr1, L, grad, acc, hit, st_face, st_pix, st_coef,
                                   stored, rl, pix_rl, bufs, stop)
            count += c
        if not grad:
            for row in range(fr0, fr1 + 1):
                if stopped(stop):
                    break
                for col in range(fc0, fc1 + 1):
                    if L[row, col] != 0.0:
                        pix = p * npix + (row // k) * cols + col // k
                        values[pix] += L[row, col] * (rl[pix] if pix_rl else ray_length(
                            p, col, row, cone, S, D, U, V, rows, cols, k, k))
    return count, stored


@jit
def raster2d(p0, p1, verts, segs, nrm, offset, fmu, S, D, U, V, N, Au, Bv, cone, rows, cols, k,
             values, weights, acc, grad, stop):
    """The 2D pass over projections ``p0..p1`` (polygon segments on a one-row detector), forward or
    gradient as :func:`raster3d`; returns the crossings. Reads ``stop`` (:func:`stopped`) per
    projection and every :data:`STOP_EVERY` segments, and returns early once it is set."""
    nv, ns = verts.shape[0], segs.shape[0]
    XY, iW = np.empty((nv, 2)), np.empty(nv)
    C = cols * k
    L = np.zeros(C)
    count = 0
    for p in range(p0, p1):
        if stopped(stop):
            return count
        project_all(verts, p, cone, S, D, N, Au, Bv, rows, cols, k, XY, iW)
        fc0, fc1, _, _ = footprint(XY, C, 1)
        if fc0 > fc1:
            continue
        for col in range(fc0, fc1 + 1):
            L[col] = weights[p * cols + col // k] * ray_length(p, col, 0, cone, S, D, U, V, 1, cols, k, 1) if grad else 0.0
        for f in range(ns):
            if f % STOP_EVERY == 0 and f > 0 and stopped(stop):
                return count
            i0, i1 = segs[f, 0], segs[f, 1]
            lo, hi = min(XY[i0, 0], XY[i1, 0]), max(XY[i0, 0], XY[i1, 0])
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
                t = (col - XY[i0, 0]) / (XY[i1, 0] - XY[i0, 0])
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
def item_face_sums(st_face, st_pix, st_coef, starts, i0, i1, weights, acc, rl, pix_rl, stop):
    """:func:`stored_face_sums` of items ``i0..i1 - 1`` from stores kept item by item: group g's
    crossings of item ``it`` are ``starts[g, it] .. starts[g, it + 1] - 1`` of the whole store.
    Item by item across the groups, so that an item's rows of ``acc`` stay in the core's cache
    (group by group, each item's rows came back from memory once per group)."""
    for it in range(i0, i1):
        for g in range(starts.shape[0]):
            a, b = starts[g, it], starts[g, it + 1]
            stored_face_sums(st_face[a:b], st_pix[a:b], st_coef[a:b], b - a, weights, acc, rl, pix_rl, stop)


@jit
def stored_face_sums(st_face, st_pix, st_coef, n, weights, acc, rl, pix_rl, stop):
    """``acc[f, j] += weights[pixel] * coef_j`` over the first ``n`` stored crossings (times the pixel's
    ray length ``rl[pixel]`` when ``pix_rl``: see :func:`raster3d`). Reads ``stop`` (:func:`stopped`)
    every :data:`STOP_EVERY` crossings and returns early once it is set.

    Block by block through :func:`stored_block` on slices, so that each block is the loop over
    ``range(len)`` of a single pass (indices numba knows to be non-negative: no wrap-around checks)."""
    for i0 in range(0, n, STOP_EVERY):
        if stopped(stop):
            return
        i1 = min(i0 + STOP_EVERY, n)
        stored_block(st_face[i0:i1], st_pix[i0:i1], st_coef[i0:i1], weights, acc, rl, pix_rl)


@jit
def stored_block(st_face, st_pix, st_coef, weights, acc, rl, pix_rl):
    """:func:`stored_face_sums` over all of the crossings given."""
    for i in range(st_face.shape[0]):
        w = weights[st_pix[i]]
        if pix_rl:
            w *= rl[st_pix[i]]
        if w != 0.0:
            f = st_face[i]
            acc[f, 0] += w * st_coef[i, 0]
            acc[f, 1] += w * st_coef[i, 1]
            acc[f, 2] += w * st_coef[i, 2]
