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

__all__ = ["available", "unavailable_reason", "NativeScene", "NativeBackend", "trace_rays"]

# enum values of Embree 4's API (rtcore_common.h, rtcore_scene.h, rtcore_buffer.h)
_GEOMETRY_TYPE_TRIANGLE = 0
_BUFFER_TYPE_INDEX, _BUFFER_TYPE_VERTEX = 0, 1
_FORMAT_UINT3, _FORMAT_FLOAT3 = 0x5003, 0x9003
_SCENE_FLAG_ROBUST = 1 << 2
_DEVICE_PROPERTY_VERSION_MAJOR = 1
_INVALID = 0xFFFFFFFF

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

    def trace_chunk(self, frames, sub, pix, far, radius, start, stop, halt):
        f, scene = frames, self.scene
        return trace_rays(self.native, pix, far, start, stop, sub, (f.s, f.d, f.u, f.v, f.cone, f.rows, f.cols),
                          scene.centre, radius, scene.face_item, scene.mu, scene.normals, halt)


def trace_rays(scene, pixel, far, start, stop, sub, frames, shift, radius, face_item, mu, normals, halt=None):
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
    halt : (1,) uint8, optional
        Stop flag (:func:`~bubsub.core.projection.backends.base.stop_flag`), read every few
        thousand rays: once it is set, the rays cast so far are returned.

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
    if halt is None:
        halt = np.zeros(1, np.uint8)
    return _state["kernel"](_state["intersect1"], scene.handle, _state["args_template"], pixel, far, start, stop, sub, s, d, u, v, bool(cone),
                            int(rows), int(cols), np.asarray(shift, float), float(radius), face_item, mu, normals, halt)


def _compile(lib):
    import numba

    from bubsub.core.projection.backends import embree_kernels as k

    # the kernels call rtcIntersect1 through its address: see embree_kernels
    address = ctypes.cast(lib.rtcIntersect1, ctypes.c_void_p).value
    # RTCIntersectArguments: flags (incoherent = 0), feature_mask (all),
    # context, filter, intersect; padded past any optional member.
    template = np.zeros(8, np.int64)
    template.view(np.uint32)[1] = 0xFFFFFFFF
    return {"kernel": k.kernel, "intersect1": int(address), "filter_address": k.record_and_reject.address,
            "args_template": template, "numba_version": numba.__version__}
