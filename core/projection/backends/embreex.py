"""The embreex ray-casting backend: closest-hit casts, re-cast just past each hit, bookkeeping in numpy.

Why the crossings are exact and counted once
-------------------------------------------
* The scene is shifted so its bounding box is centred on the origin and every
  ray starts just before that box. Float32 then resolves positions relative to
  the scene's size, whatever the source distance (300 mm or 50 m) or the
  scene's offset from the world origin.
* After a hit the ray restarts ``eps = 1e-5 x scene size`` past it. That is far
  above float32 round-off, so a ray cannot hit the same triangle twice; a ray
  through a shared edge can still report both triangles.
* Crossings are then paired per ray and per mesh: a closed, outward mesh is
  entered (n.d < 0) and left (n.d > 0) alternately. An enter counts only when
  the next crossing of that mesh is an exit, and vice versa. Doubled crossings
  (edges, vertices) and a tangent pair closer than ``eps`` (one of which may be
  skipped) then contribute at most ``eps`` instead of a whole chord.

2D scans are cast in the plane z = 0 through each polygon extruded into a prism.
"""

from __future__ import annotations

import numpy as np

from bubsub.core.projection.backends.frames import RayCaster

__all__ = ["EmbreexBackend"]


def _embree():
    try:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except ImportError as exc:  # pragma: no cover - embreex is a hard dependency
        raise ImportError("the mesh projector needs embreex (pip install embreex)") from exc
    return rtcore_scene, TriangleMesh


class EmbreexBackend(RayCaster):
    """Closest-hit casting through embreex, once per crossing."""

    name = "embreex"

    def prepare(self, scene, eps):
        return _EmbreexScene(scene, eps)


class _EmbreexScene:
    def __init__(self, scene, eps):
        self.scene = scene
        self.eps = eps
        self.normals32 = scene.normals.astype(np.float32)  # cosines in float32, like the rays
        rtcs, TriangleMesh = _embree()
        self.embree = rtcs.EmbreeScene(robust=True)
        TriangleMesh(self.embree, scene.vertices.astype(np.float32), scene.faces.astype(np.int32))
        # commit now: concurrent first queries would each try to commit
        one = np.zeros((1, 3), np.float32)
        self.embree.run(one, one + np.float32(1), output=1)

    def trace_chunk(self, frames, sub, pix, far, radius, start, stop, halt):
        """Trace rays ``start:stop``; returns (first pixel, values from it, crossings). Once the stop flag
        ``halt`` is set it returns what it has (read before each pass of closest-hit casts)."""
        scene = self.scene
        k2 = sub.shape[0]
        ray = np.arange(start, stop)
        which = slice(start, stop) if k2 == 1 else ray // k2
        pixel = pix[which]
        od, length = frames.rays(pixel, sub[ray % k2], scene.centre, radius, far[which])
        idx = np.arange(len(od))  # ray of each still active row
        toff = np.zeros(len(od))
        hit_ray, hit_prim, hit_t, hit_u, hit_v, hit_cos = [], [], [], [], [], []
        eps = self.eps
        normals = self.normals32
        while idx.size and not halt[0]:
            res = self.embree.run(od[:, :3], od[:, 3:], dists=(length - toff).astype(np.float32), output=1)
            h = np.flatnonzero(res["primID"] >= 0)
            prim = res["primID"][h]
            t = res["tfar"][h].astype(np.float64)
            idx, od, length = idx[h], od[h], length[h]
            toff = toff[h] + t
            hit_ray.append(idx)
            hit_prim.append(prim)
            hit_t.append(toff)
            hit_u.append(res["u"][h])
            hit_v.append(res["v"][h])
            hit_cos.append(np.einsum("ij,ij->i", normals[prim], od[:, 3:]))
            toff = toff + eps  # restart just past the hit
            od[:, :3] += ((t + eps)[:, None] * od[:, 3:]).astype(np.float32)
            more = toff < length
            if not more.all():
                idx, toff, od, length = idx[more], toff[more], od[more], length[more]
        lo = int(pixel[0]) if pixel.size else 0
        if not hit_ray:
            e = np.empty(0)
            return lo, e, (e.astype(np.int64), e.astype(np.int32), np.empty((0, 3), np.float32), e.astype(np.float32))
        r = np.concatenate(hit_ray)
        face = np.concatenate(hit_prim)
        t = np.concatenate(hit_t)
        u = np.concatenate(hit_u)
        v = np.concatenate(hit_v)
        cos = np.concatenate(hit_cos)
        exiting = cos > 0
        item = scene.face_item[face]
        # Stable sort by (ray, item): hits of one ray were recorded in t order.
        order = np.argsort(r * len(scene.items) + item, kind="stable")
        r, face, t, u, v, cos, exiting, item = (a[order] for a in (r, face, t, u, v, cos, exiting, item))
        same_next = np.zeros(r.size, bool)
        same_next[:-1] = (r[1:] == r[:-1]) & (item[1:] == item[:-1])
        ok = ~exiting & same_next  # an entry followed by an exit of the same mesh
        ok[:-1] &= exiting[1:]
        ok[1:] |= ok[:-1]  # ... and that exit
        r, face, t, u, v, cos, exiting = (a[ok] for a in (r, face, t, u, v, cos, exiting))
        px = pixel[r]
        part = np.bincount(px - lo, weights=scene.mu[scene.face_item[face]] * np.where(exiting, t, -t))
        with np.errstate(divide="ignore"):
            inv_cos = (1.0 / np.abs(cos)).astype(np.float32)
        bary = np.stack([1.0 - u - v, u, v], axis=1).astype(np.float32)
        return lo, part, (px, face.astype(np.int32), bary, inv_cos)
