"""The compiled ray-casting backend: Embree 4 called directly, driven by numba.

embreex returns the closest hit of each ray, so collecting every crossing
through it means one Python-level pass (and one BVH traversal) per crossing.
This backend loads the Embree 4 library that the embreex wheel ships, attaches
an intersection *filter* to the scene that records every candidate hit and
rejects it, so a single traversal per ray yields all its crossings, and runs
the per-ray loop (ray set-up, cast, sort, pairing, reduction) as compiled
numba code that releases the GIL.

Only a few plain C structs of Embree 4's API are used (``RTCRayHit``,
``RTCIntersectArguments``, ``RTCFilterFunctionNArguments``); their layouts are
written out below. :func:`available` says whether the backend can run here
(numba importable, an Embree 4 library found and answering as version 4);
when it cannot, ``backend="auto"`` does not choose it.
"""

from __future__ import annotations

import ctypes
import glob
import os

import numpy as np

from bubsub.core.projection.backends.frames import RayCaster
from bubsub.core.projection.backends.jit import cached

__all__ = ["available", "unavailable_reason", "NativeScene", "NativeBackend", "trace_rays"]

# enum values of Embree 4's API (rtcore_common.h, rtcore_scene.h, rtcore_buffer.h)
_GEOMETRY_TYPE_TRIANGLE = 0
_BUFFER_TYPE_INDEX, _BUFFER_TYPE_VERTEX = 0, 1
_FORMAT_UINT3, _FORMAT_FLOAT3 = 0x5003, 0x9003
_SCENE_FLAG_ROBUST = 1 << 2
_DEVICE_PROPERTY_VERSION_MAJOR = 1
_INVALID = 0xFFFFFFFF
_HIT_CAPACITY = 256  # recorded hits per ray before the buffer grows (and the ray is re-cast)

_state = {}


def _library_candidates():
    try:
        import embreex
    except ImportError:
        return []
    base = os.path.dirname(os.path.abspath(embreex.__file__))
    patterns = [os.path.join(base, os.pardir, "embreex.libs", "libembree4*"),  # manylinux wheels
                os.path.join(base, ".dylibs", "libembree4*"),  # macOS wheels
                os.path.join(base, "*embree4*"), os.path.join(base, os.pardir, "embreex.libs", "*embree4*")]
    found = []
    for p in patterns:
        found += sorted(glob.glob(p))
    return list(dict.fromkeys(os.path.normpath(f) for f in found))


def _load():
    """Load numba, the Embree library and the compiled functions once; record why not."""
    if "ok" in _state:
        return _state["ok"]
    _state["ok"] = False
    try:
        import numba  # noqa: F401
    except ImportError:
        _state["why"] = "numba is not installed"
        return False
    paths = _library_candidates()
    if not paths:
        _state["why"] = "no Embree 4 library found next to embreex"
        return False
    try:
        lib = ctypes.CDLL(paths[0])
        _declare(lib)
        device = lib.rtcNewDevice(None)
        if not device:
            raise OSError("rtcNewDevice failed")
        major = lib.rtcGetDeviceProperty(device, _DEVICE_PROPERTY_VERSION_MAJOR)
        if major != 4:
            raise OSError(f"{paths[0]} is Embree {major}, not 4")
    except (OSError, AttributeError) as exc:
        _state["why"] = f"cannot use the Embree library: {exc}"
        return False
    _state.update(lib=lib, device=device, path=paths[0])
    _state.update(_compile(lib))
    _state["ok"] = True
    return True


def available():
    """Whether the compiled backend can run in this environment."""
    return _load()


def unavailable_reason():
    """Why :func:`available` is False ("" when it is True)."""
    return "" if _load() else _state.get("why", "unknown")


def _declare(lib):
    vp, sz, ui, i = ctypes.c_void_p, ctypes.c_size_t, ctypes.c_uint, ctypes.c_int
    for name, res, args in [
        ("rtcNewDevice", vp, [ctypes.c_char_p]),
        ("rtcGetDeviceProperty", ctypes.c_ssize_t, [vp, i]),
        ("rtcGetDeviceError", i, [vp]),
        ("rtcNewScene", vp, [vp]),
        ("rtcSetSceneFlags", None, [vp, i]),
        ("rtcNewGeometry", vp, [vp, i]),
        ("rtcSetSharedGeometryBuffer", None, [vp, i, ui, i, vp, sz, sz, sz]),
        ("rtcSetGeometryIntersectFilterFunction", None, [vp, vp]),
        ("rtcCommitGeometry", None, [vp]),
        ("rtcAttachGeometry", ui, [vp, vp]),
        ("rtcReleaseGeometry", None, [vp]),
        ("rtcCommitScene", None, [vp]),
        ("rtcReleaseScene", None, [vp]),
    ]:
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = res, args


class NativeScene:
    """An Embree 4 scene of one triangle soup, with the hit-recording filter attached.

    Parameters
    ----------
    vertices : (n, 3) float
        Already shifted near the origin (float32 precision is relative to it).
    faces : (m, 3) int
    """

    def __init__(self, vertices, faces):
        if not _load():
            raise RuntimeError(f"the compiled ray-casting backend is unavailable: {unavailable_reason()}")
        lib, device = _state["lib"], _state["device"]
        # Embree reads vertex buffers 16 bytes at a time: pad one vertex
        self._vertices = np.zeros((len(vertices) + 1, 3), np.float32)
        self._vertices[:-1] = vertices
        self._faces = np.ascontiguousarray(faces, dtype=np.uint32)
        scene = lib.rtcNewScene(device)
        lib.rtcSetSceneFlags(scene, _SCENE_FLAG_ROBUST)
        geom = lib.rtcNewGeometry(device, _GEOMETRY_TYPE_TRIANGLE)
        lib.rtcSetSharedGeometryBuffer(geom, _BUFFER_TYPE_INDEX, 0, _FORMAT_UINT3, self._faces.ctypes.data, 0, 12, len(self._faces))
        lib.rtcSetSharedGeometryBuffer(geom, _BUFFER_TYPE_VERTEX, 0, _FORMAT_FLOAT3, self._vertices.ctypes.data, 0, 12, len(vertices))
        lib.rtcSetGeometryIntersectFilterFunction(geom, _state["filter_address"])
        lib.rtcCommitGeometry(geom)
        lib.rtcAttachGeometry(scene, geom)
        lib.rtcReleaseGeometry(geom)
        lib.rtcCommitScene(scene)
        err = lib.rtcGetDeviceError(device)
        if err:
            lib.rtcReleaseScene(scene)
            raise RuntimeError(f"Embree could not build the scene (error code {err})")
        self.handle = int(scene)

    def __del__(self):
        handle, self.handle = getattr(self, "handle", 0), 0
        if handle and _state.get("lib") is not None:
            _state["lib"].rtcReleaseScene(handle)


class NativeBackend(RayCaster):
    """All of a ray's crossings from one Embree traversal, recorded by an intersection filter."""

    name = "native"

    def prepare(self, scene, eps):
        return _NativeCaster(scene)


class _NativeCaster:
    def __init__(self, scene):
        self.scene = scene
        self.native = NativeScene(scene.vertices, scene.faces)

    def trace_chunk(self, frames, sub, pix, far, radius, start, stop):
        f, scene = frames, self.scene
        return trace_rays(self.native, pix, far, start, stop, sub, (f.s, f.d, f.u, f.v, f.cone, f.rows, f.cols),
                          scene.centre, radius, scene.face_item, scene.mu, scene.normals)


def trace_rays(scene, pixel, far, start, stop, sub, frames, shift, radius, face_item, mu, normals):
    """Cast rays ``start:stop`` of the candidate pixels; every valid crossing, paired.

    Parameters
    ----------
    scene : NativeScene
    pixel : (k,) int64
        Sorted flat candidate pixels; ray ``q`` belongs to ``pixel[q // len(sub)]``.
    far : (k,) float
        Per pixel: how far from the ray's start a crossing can be (see
        ``Frames.candidate_pixels``), padded.
    sub : (k2, 2) float
        Sub-ray offsets in pixel units.
    frames : tuple
        ``(s, d, u, v, cone, rows, cols)``: per-projection source or ray,
        detector centre and axes as (n, 3) float arrays.
    shift : (3,) float
        The scene's centre; rays are expressed relative to it.
    radius : float
        Rays start on the sphere of this radius about ``shift``.
    face_item : (m,) int64, mu : (n_items,) float, normals : (m, 3) float

    Returns
    -------
    lo : int
        First pixel of the chunk.
    part : (p,) float
        Values of pixels ``lo, lo + 1, ...`` (sum over sub-rays).
    crossings : tuple
        ``pixel (c,) int64, face (c,) int32, bary (c, 3) float32, inv_cos (c,) float32``.
    """
    s, d, u, v, cone, rows, cols = frames
    return _state["kernel"](_state["intersect1"], scene.handle, _state["args_template"], pixel, far, start, stop, sub, s, d, u, v, bool(cone),
                            int(rows), int(cols), np.asarray(shift, float), float(radius), face_item, mu, normals)


def _compile(lib):
    import numba
    from numba import carray, cfunc, types
    from numba.extending import intrinsic

    def pointer_to(ty):
        @intrinsic
        def to_pointer(typingctx, address):
            sig = types.CPointer(ty)(address)

            def codegen(context, builder, signature, args):
                return builder.inttoptr(args[0], context.get_value_type(signature.return_type))

            return sig, codegen

        return to_pointer

    f32p, u32p, i32p, i64p = (pointer_to(t) for t in (types.float32, types.uint32, types.int32, types.int64))

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

    intersect1 = ctypes.CFUNCTYPE(None, ctypes.c_size_t, ctypes.c_size_t, ctypes.c_size_t)(("rtcIntersect1", lib))

    @cached(numba.njit, nogil=True)
    def hit_buffers(cap):
        """The filter's record (t, primID, u, v per hit) and the per-ray work arrays."""
        return (np.zeros(4 * cap, np.float32), np.empty(cap), np.empty(cap, np.int64), np.empty(cap), np.empty(cap),
                np.empty(cap), np.empty(cap, np.int64), np.zeros(cap, np.bool_))

    @cached(numba.njit, nogil=True)
    def kernel(intersect1, handle, args_template, pixel, far, start, stop, sub, S, D, U, V, cone, rows, cols, shift, radius, face_item, mu, normals):
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
        cap = _HIT_CAPACITY
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
                intersect1(handle, rh_ptr, args_ptr)
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

    # RTCIntersectArguments: flags (incoherent = 0), feature_mask (all),
    # context, filter, intersect; padded past any optional member.
    template = np.zeros(8, np.int64)
    template.view(np.uint32)[1] = 0xFFFFFFFF
    return {"kernel": kernel, "intersect1": intersect1, "filter_address": record_and_reject.address, "args_template": template, "numba_version": numba.__version__}
