"""Compiled voxel-driven splatting and its exact transpose, for :class:`~bubsub.core.voxel.projector3d.VoxelProjector`.

For every voxel centre and projection the detector position is a ratio of
affine functions (cone) or affine (parallel), as set up by ``_Maps``; the
voxel's value times its weight is spread bilinearly over the four nearest
(virtual) detector pixels of a detector padded by 1 (low) / 2 (high) pixels,
so positions off the detector land in the margin. The gather does exactly the
transposed arithmetic. Both loop over voxels in compiled code (numba, no
temporaries per slab), which is about 10x faster and far lighter on memory
than the numpy version this replaced (per slab and projection: seven float32
arrays and four ``bincount`` passes).
"""

from __future__ import annotations

import numpy as np

from bubsub.core.projection.backends.jit import cached

__all__ = ["splat", "gather"]

_kernels = {}


def _compile():
    import numba

    jit = cached(numba.njit, nogil=True, error_model="numpy")

    @jit
    def position(i, xx, yy, zz, cone, den, col, row, amp, wfdk, src, fdk_weight):
        """Detector (col, row) of a voxel centre in projection i, and its weight."""
        c = col[i, 0] * xx + col[i, 1] * yy + col[i, 2] * zz + col[i, 3]
        r = row[i, 0] * xx + row[i, 1] * yy + row[i, 2] * zz + row[i, 3]
        if not cone:
            return c, r, wfdk[i] if fdk_weight else amp[i]
        inv = 1.0 / (den[i, 0] * xx + den[i, 1] * yy + den[i, 2] * zz + den[i, 3])
        if fdk_weight:
            return c * inv, r * inv, wfdk[i] * inv * inv
        dx, dy, dz = xx - src[i, 0], yy - src[i, 1], zz - src[i, 2]
        return c * inv, r * inv, np.sqrt(dx * dx + dy * dy + dz * dz) * amp[i] * inv * inv * inv

    @jit
    def bilinear(c, r, rows, cols):
        """Flat index into the padded detector (width cols + 3) and the bilinear fractions."""
        cc = min(max(c + 1.0, 0.0), cols + 1.0)
        rr = min(max(r + 1.0, 0.0), rows + 1.0)
        i0, j0 = int(cc), int(rr)
        return j0 * (cols + 3) + i0, cc - i0, rr - j0

    @jit
    def splat_kernel(vol, z0, z1, x, y, z, cone, den, col, row, amp, wfdk, src, rows, cols, acc):
        n = acc.shape[0]
        wp = cols + 3
        for iz in range(z0, z1):
            for iy in range(y.shape[0]):
                for ix in range(x.shape[0]):
                    v = vol[iz, iy, ix]
                    if v == 0.0:
                        continue
                    for i in range(n):
                        c, r, w = position(i, x[ix], y[iy], z[iz], cone, den, col, row, amp, wfdk, src, False)
                        idx, fu, fv = bilinear(c, r, rows, cols)
                        val = v * w
                        v1 = val * fv
                        v0 = val - v1
                        acc[i, idx] += v0 * (1.0 - fu)
                        acc[i, idx + 1] += v0 * fu
                        acc[i, idx + wp] += v1 * (1.0 - fu)
                        acc[i, idx + wp + 1] += v1 * fu

    @jit
    def gather_kernel(out, z0, z1, x, y, z, cone, den, col, row, amp, wfdk, src, rows, cols, pad, skip, fdk_weight):
        n = pad.shape[0]
        wp = cols + 3
        for iz in range(z0, z1):
            for iy in range(y.shape[0]):
                for ix in range(x.shape[0]):
                    total = 0.0
                    for i in range(n):
                        if skip[i]:
                            continue
                        c, r, w = position(i, x[ix], y[iy], z[iz], cone, den, col, row, amp, wfdk, src, fdk_weight)
                        idx, fu, fv = bilinear(c, r, rows, cols)
                        top = pad[i, idx] * (1.0 - fu) + pad[i, idx + 1] * fu
                        bot = pad[i, idx + wp] * (1.0 - fu) + pad[i, idx + wp + 1] * fu
                        total += w * (top * (1.0 - fv) + bot * fv)
                    out[iz, iy, ix] += total

    return {"splat": splat_kernel, "gather": gather_kernel}


def _get(name):
    if not _kernels:
        _kernels.update(_compile())
    return _kernels[name]


def _map_args(m):
    cone = bool(m.cone)
    den = m.den if cone else np.zeros((m.n, 4))
    src = m.src if cone else np.zeros((m.n, 3))
    amp = np.broadcast_to(np.asarray(m.amp, dtype=float), (m.n,)).copy()
    return (np.asarray(m.x, float), np.asarray(m.y, float), np.asarray(m.z, float), cone, np.ascontiguousarray(den, float),
            np.ascontiguousarray(m.col, float), np.ascontiguousarray(m.row, float), amp,
            np.ascontiguousarray(m.fdk_w, float), np.ascontiguousarray(src, float))


def splat(maps, vol, z0, z1, acc):
    """Add the projections of slices ``z0:z1`` of ``vol`` to ``acc`` ((n, (rows + 3) (cols + 3)) float64, padded)."""
    _get("splat")(vol, z0, z1, *_map_args(maps), maps.rows, maps.cols, acc)


def gather(maps, pad, z0, z1, out, weight="amp", skip=None):
    """Add to ``out[z0:z1]`` the weighted bilinear gather of the padded projections ``pad`` ((n, L) float32)."""
    skip = np.zeros(maps.n, np.bool_) if skip is None else np.asarray(skip, np.bool_)
    _get("gather")(out, z0, z1, *_map_args(maps), maps.rows, maps.cols, pad, skip, weight == "fdk")
