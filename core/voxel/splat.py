"""Compiled voxel-driven splatting and its exact transpose, for :class:`~bubsub.core.voxel.projector3d.VoxelProjector`.

For every voxel centre and projection the detector position is a ratio of
affine functions (cone) or affine (parallel), as set up by ``_Maps``; the
voxel's value times its weight is spread bilinearly over the four nearest
(virtual) detector pixels of a detector padded by 1 (low) / 2 (high) pixels,
so positions off the detector land in the margin. The gather does exactly the
transposed arithmetic. Both loop over voxels in compiled code (numba, no
temporaries per slab), about 10x faster and far lighter on memory than the
same arithmetic in numpy (per slab and projection: seven float32 arrays and
four ``bincount`` passes).
"""

from __future__ import annotations

import numpy as np

__all__ = ["splat", "gather"]

_kernels = {}


def _compile():
    from bubsub.core.voxel import splat_kernels

    return {"splat": splat_kernels.splat_kernel, "gather": splat_kernels.gather_kernel}


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
