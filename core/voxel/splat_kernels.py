"""The voxel splat's compiled kernels (numba), at module level so that numba's disk cache hits.

Kept apart from :mod:`.splat` so that numba is imported only when the voxel
projector runs. Defined at module level rather than in a factory: numba's
cache key hashes a closure's captured variables, and captured dispatchers
serialise differently in every process, so closures would be compiled again
in each one.
"""

from __future__ import annotations

import numba
import numpy as np

from bubsub.core.projection.backends.jit import cached

__all__ = ["splat_kernel", "gather_kernel"]

# numpy error model: float division by zero gives inf instead of a checked exception
jit = cached(numba.njit, nogil=True, error_model="numpy")


@jit
def store(ix, c, r, wt, rows, cols, idx, fu, fv, w):
    """Bilinear index into the padded detector (width cols + 3), fractions and weight of voxel ix."""
    cc = min(max(c + 1.0, 0.0), cols + 1.0)
    rr = min(max(r + 1.0, 0.0), rows + 1.0)
    i0, j0 = int(cc), int(rr)
    idx[ix] = j0 * (cols + 3) + i0
    fu[ix] = cc - i0
    fv[ix] = rr - j0
    w[ix] = wt


@jit
def row_positions(i, iz, iy, x, y, z, cone, den, col, row, amp, wfdk, src, rows, cols, fdk_weight, idx, fu, fv, w):
    """Detector position and weight of every voxel of row (iz, iy) in projection i.

    The column (or row) of a voxel centre is an affine function over a
    denominator affine in it (cone) or just affine (parallel). One branch
    per case outside the loops, and no memory dependencies inside, so the
    compiler vectorises the divisions and roots.
    """
    yy, zz = y[iy], z[iz]
    c0, cx = col[i, 1] * yy + col[i, 2] * zz + col[i, 3], col[i, 0]
    r0, rx = row[i, 1] * yy + row[i, 2] * zz + row[i, 3], row[i, 0]
    if not cone:
        wt = wfdk[i] if fdk_weight else amp[i]
        for ix in range(x.shape[0]):
            store(ix, c0 + cx * x[ix], r0 + rx * x[ix], wt, rows, cols, idx, fu, fv, w)
        return
    d0, dx = den[i, 1] * yy + den[i, 2] * zz + den[i, 3], den[i, 0]
    if fdk_weight:
        for ix in range(x.shape[0]):
            inv = 1.0 / (d0 + dx * x[ix])
            store(ix, (c0 + cx * x[ix]) * inv, (r0 + rx * x[ix]) * inv, wfdk[i] * inv * inv, rows, cols, idx, fu, fv, w)
        return
    sy, sz = (yy - src[i, 1]) ** 2, (zz - src[i, 2]) ** 2
    for ix in range(x.shape[0]):
        inv = 1.0 / (d0 + dx * x[ix])
        dist = np.sqrt((x[ix] - src[i, 0]) ** 2 + sy + sz)
        store(ix, (c0 + cx * x[ix]) * inv, (r0 + rx * x[ix]) * inv, dist * amp[i] * inv * inv * inv,
              rows, cols, idx, fu, fv, w)


@jit
def splat_kernel(vol, z0, z1, x, y, z, cone, den, col, row, amp, wfdk, src, rows, cols, acc):
    wp = cols + 3
    nx = x.shape[0]
    idx, fu, fv, w = np.empty(nx, np.int64), np.empty(nx), np.empty(nx), np.empty(nx)
    # projection outermost: neighbouring voxels hit neighbouring pixels, which stay in cache
    for i in range(acc.shape[0]):
        for iz in range(z0, z1):
            for iy in range(y.shape[0]):
                row_positions(i, iz, iy, x, y, z, cone, den, col, row, amp, wfdk, src, rows, cols, False, idx, fu, fv, w)
                for ix in range(nx):
                    v = vol[iz, iy, ix]
                    if v == 0.0:
                        continue
                    val = v * w[ix]
                    v1 = val * fv[ix]
                    v0 = val - v1
                    k = idx[ix]
                    acc[i, k] += v0 * (1.0 - fu[ix])
                    acc[i, k + 1] += v0 * fu[ix]
                    acc[i, k + wp] += v1 * (1.0 - fu[ix])
                    acc[i, k + wp + 1] += v1 * fu[ix]


@jit
def gather_kernel(out, z0, z1, x, y, z, cone, den, col, row, amp, wfdk, src, rows, cols, pad, skip, fdk_weight):
    wp = cols + 3
    nx = x.shape[0]
    idx, fu, fv, w = np.empty(nx, np.int64), np.empty(nx), np.empty(nx), np.empty(nx)
    total = np.empty(nx)
    # a local row accumulator: writing into ``out`` inside the loop would order every load after the
    # previous store (the compiler cannot prove they never alias), about 5x slower
    for iz in range(z0, z1):
        for iy in range(y.shape[0]):
            total[:] = 0.0
            for i in range(pad.shape[0]):
                if skip[i]:
                    continue
                row_positions(i, iz, iy, x, y, z, cone, den, col, row, amp, wfdk, src, rows, cols, fdk_weight, idx, fu, fv, w)
                for ix in range(nx):
                    k = idx[ix]
                    top = pad[i, k] * (1.0 - fu[ix]) + pad[i, k + 1] * fu[ix]
                    bot = pad[i, k + wp] * (1.0 - fu[ix]) + pad[i, k + wp + 1] * fu[ix]
                    total[ix] += w[ix] * (top * (1.0 - fv[ix]) + bot * fv[ix])
            for ix in range(nx):
                out[iz, iy, ix] += total[ix]
