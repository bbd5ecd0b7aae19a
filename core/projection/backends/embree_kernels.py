"""The compiled backend's numba code, at module level so that numba's disk cache hits.

Kept apart from :mod:`.embree_native` so that numba is imported only when the
backend is used. Nothing process-specific may enter a compiled function's
type or numba's cache key (a closure's captured values do, and a ctypes
function of ``rtcIntersect1`` differs from process to process): it would be
compiled again in every process (seconds) with a new cache file each time. So
the functions live at module level and ``rtcIntersect1`` is called through
its address, an integer argument (:func:`call3`).
See :mod:`bubsub.core.projection.backends.embree_native` for the method.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba import carray, cfunc, types
from numba.extending import intrinsic

from bubsub.core.projection.backends.jit import cached

__all__ = ["HIT_CAPACITY", "call3", "record_and_reject", "hit_buffers", "kernel"]

HIT_CAPACITY = 256  # recorded hits per ray before the buffer grows (and the ray is re-cast)
HALT_EVERY = 4096  # rays between two reads of the stop flag (kernel)
jit = cached(numba.njit, nogil=True)


def _pointer_to(ty):
    """An intrinsic turning an int64 address into a ``ty*`` (for ``carray``)."""

    @intrinsic
    def to_pointer(typingctx, address):
        sig = types.CPointer(ty)(address)

        def codegen(context, builder, signature, args):
            return builder.inttoptr(args[0], context.get_value_type(signature.return_type))

        return sig, codegen

    return to_pointer


f32p, u32p, i32p, i64p = (_pointer_to(t) for t in (types.float32, types.uint32, types.int32, types.int64))


@intrinsic
def call3(typingctx, address, a, b, c):
    """Call the C function ``void f(size_t, size_t, size_t)`` at ``address`` (all four int64)."""
    sig = types.void(types.int64, types.int64, types.int64, types.int64)

    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(ir.VoidType(), [ir.IntType(64)] * 3)
        fn = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(fn, args[1:])
        return context.get_dummy_value()

    return sig, codegen


# RTCFilterFunctionNArguments: int* valid; void* geometryUserPtr;
# RTCRayQueryContext* context; RTCRayN* ray; RTCHitN* hit; unsigned N.
# Our context is the RTCRayQueryContext header (16 bytes) followed by
# int64 [buffer address, hit count, capacity]. Each recorded hit is
# (float t, uint primID, float u, float v).
@cached(cfunc, sig=types.void(types.CPointer(types.int64)), nopython=True)
def record_and_reject(args):
    n = args[5] & 0xFFFFFFFF
    valid = carray(i32p(args[0]), (n,))
    ctx = carray(i64p(args[2] + 16), (3,))
    ray = carray(f32p(args[3]), (12 * n,))
    hitf = carray(f32p(args[4]), (8 * n,))
    hitu = carray(u32p(args[4]), (8 * n,))
    buf_f = carray(f32p(ctx[0]), (4 * ctx[2],))
    buf_u = carray(u32p(ctx[0]), (4 * ctx[2],))
    for i in range(n):
        if valid[i] == 0:
            continue
        k = ctx[1]
        if k < ctx[2]:
            buf_f[4 * k] = ray[8 * n + i]  # tfar: the hit's distance
            buf_u[4 * k + 1] = hitu[5 * n + i]  # primID
            buf_f[4 * k + 2] = hitf[3 * n + i]  # u
            buf_f[4 * k + 3] = hitf[4 * n + i]  # v
        ctx[1] = k + 1
        valid[i] = 0  # reject: traversal goes on to the next hit


@jit
def hit_buffers(cap):
    """The filter's record (t, primID, u, v per hit) and the per-ray work arrays."""
    return (np.zeros(4 * cap, np.float32), np.empty(cap), np.empty(cap, np.int64), np.empty(cap), np.empty(cap),
            np.empty(cap), np.empty(cap, np.int64), np.zeros(cap, np.bool_))


@jit
def kernel(intersect1, handle, args_template, pixel, far, start, stop, sub, S, D, U, V, cone, rows, cols, shift, radius, face_item, mu, normals,
           halt):
    """Cast rays ``start:stop`` (see :func:`~bubsub.core.projection.backends.embree_native.trace_rays`).

    ``halt`` ((1,) uint8, :func:`~bubsub.core.projection.backends.base.stop_flag`) is read every
    :data:`HALT_EVERY` rays; once it is set the rays cast so far are returned. A plain read suffices:
    every ray calls into Embree, which the compiler must assume may write any memory, so the byte
    is read afresh after it."""
    k2 = sub.shape[0]
    npix = rows * cols
    # RTCRayHit (16-byte aligned): ray org 0-2, tnear 3, dir 4-6, time 7,
    # tfar 8, mask 9, id 10, flags 11; hit Ng 12-14, u 15, v 16, primID 17,
    # geomID 18, instID 19 (+ instPrimID 20), as 32-bit words.
    raw = np.zeros(128, np.float32)
    o = ((16 - raw.ctypes.data % 16) % 16) // 4
    rh = raw[o:o + 64]
    rhu = rh.view(np.uint32)
    rh_ptr = raw.ctypes.data + 4 * o
    cap = HIT_CAPACITY
    hits, t, prim, uu, vv, cosv, item, dup = hit_buffers(cap)
    hitsu = hits.view(np.uint32)
    ctx = np.zeros(8, np.int64)  # 16-byte RTCRayQueryContext, then buffer, count, capacity
    ctx[2] = hits.ctypes.data
    ctx[4] = cap
    args = args_template.copy()  # RTCIntersectArguments; context pointer at byte 8
    args[1] = ctx.ctypes.data
    args_ptr = args.ctypes.data

    lo = pixel[start // k2] if stop > start else 0
    hi = pixel[(stop - 1) // k2] if stop > start else -1
    part = np.zeros(hi - lo + 1)
    n_out = 0
    out_cap = 4 * (stop - start) + 16
    o_px = np.empty(out_cap, np.int64)
    o_face = np.empty(out_cap, np.int32)
    o_bary = np.empty((out_cap, 3), np.float32)
    o_inv = np.empty(out_cap, np.float32)
    org = np.empty(3)
    dirv = np.empty(3)
    for q in range(start, stop):
        if (q - start) % HALT_EVERY == 0 and halt[0] != 0:
            break
        px = pixel[q // k2]
        j = q % k2
        p = px // npix
        rem = px - p * npix
        r = rem // cols
        c = rem - r * cols
        a = c + 0.5 - cols / 2 + sub[j, 0]
        b = r + 0.5 - rows / 2 + sub[j, 1]
        if cone:
            nn = 0.0
            for x in range(3):
                dirv[x] = (D[p, x] - S[p, x]) + a * U[p, x] + b * V[p, x]
                nn += dirv[x] * dirv[x]
            nn = np.sqrt(nn)
            tc = 0.0
            for x in range(3):
                dirv[x] /= nn
                org[x] = S[p, x] - shift[x]
                tc -= dirv[x] * org[x]
        else:
            nn = np.sqrt(S[p, 0] ** 2 + S[p, 1] ** 2 + S[p, 2] ** 2)
            tc = 0.0
            for x in range(3):
                dirv[x] = S[p, x] / nn
                org[x] = (D[p, x] - shift[x]) + a * U[p, x] + b * V[p, x]
                tc -= org[x] * dirv[x]
        t0 = tc - radius
        length = far[q // k2] - t0 if cone else far[q // k2] + radius
        length = min(length, 2 * radius)
        if length <= 0:
            continue
        while True:
            for x in range(3):
                rh[x] = org[x] + t0 * dirv[x]
                rh[4 + x] = dirv[x]
            rh[3] = 0.0
            rh[7] = 0.0
            rh[8] = length
            rhu[9] = 0xFFFFFFFF
            rhu[10] = 0
            rhu[11] = 0
            rhu[17] = 0xFFFFFFFF
            rhu[18] = 0xFFFFFFFF
            ctx[3] = 0
            call3(intersect1, handle, rh_ptr, args_ptr)
            m = ctx[3]
            if m <= cap:
                break
            # more crossings than the buffer holds: grow it and cast again
            cap = 2 * m
            hits, t, prim, uu, vv, cosv, item, dup = hit_buffers(cap)
            hitsu = hits.view(np.uint32)
            ctx[2] = hits.ctypes.data
            ctx[4] = cap
        if m == 0:
            continue
        # the filter sees hits in traversal order: insertion-sort them by distance
        for h in range(m):
            th = np.float64(hits[4 * h])
            ph = np.int64(hitsu[4 * h + 1])
            uh = np.float64(hits[4 * h + 2])
            vh = np.float64(hits[4 * h + 3])
            g = h
            while g > 0 and (t[g - 1] > th or (t[g - 1] == th and prim[g - 1] > ph)):
                t[g] = t[g - 1]
                prim[g] = prim[g - 1]
                uu[g] = uu[g - 1]
                vv[g] = vv[g - 1]
                g -= 1
            t[g] = th
            prim[g] = ph
            uu[g] = uh
            vv[g] = vh
        for h in range(m):
            f = prim[h]
            cosv[h] = normals[f, 0] * dirv[0] + normals[f, 1] * dirv[1] + normals[f, 2] * dirv[2]
            item[h] = face_item[f]
            # a triangle referenced twice by the BVH reports the same hit twice
            dup[h] = h > 0 and prim[h - 1] == f and t[h - 1] == t[h]
        # A closed outward mesh is entered (cos <= 0) and left (cos > 0) in
        # turn: an entry counts only when the next crossing of that mesh is
        # an exit, together with that exit. Doubled hits at shared edges
        # and tangent pairs then cost at most their tiny separation.
        for h in range(m):
            if dup[h] or cosv[h] > 0:
                continue
            g = h + 1
            while g < m and (dup[g] or item[g] != item[h]):
                g += 1
            if g == m or cosv[g] <= 0:
                continue
            part[px - lo] += mu[item[h]] * (t[g] - t[h])
            if n_out + 2 > out_cap:
                out_cap = 2 * out_cap
                o_px = np.concatenate((o_px, np.empty(out_cap - o_px.shape[0], np.int64)))
                o_face = np.concatenate((o_face, np.empty(out_cap - o_face.shape[0], np.int32)))
                o_bary = np.concatenate((o_bary, np.empty((out_cap - o_bary.shape[0], 3), np.float32)))
                o_inv = np.concatenate((o_inv, np.empty(out_cap - o_inv.shape[0], np.float32)))
            for e in (h, g):
                o_px[n_out] = px
                o_face[n_out] = prim[e]
                o_bary[n_out, 0] = 1.0 - uu[e] - vv[e]
                o_bary[n_out, 1] = uu[e]
                o_bary[n_out, 2] = vv[e]
                o_inv[n_out] = 1.0 / abs(cosv[e]) if cosv[e] != 0 else np.inf
                n_out += 1
    return lo, part, (o_px[:n_out], o_face[:n_out], o_bary[:n_out], o_inv[:n_out])
