"""The paper's 4D voxel baseline: per subscan, 30 Barzilai-Borwein projected-gradient iterations, x >= 0.

Each subscan is reconstructed on its own (no temporal coupling) from the
projections BubSub fits, and scored on the held-out ones by the projection
MSE (paper figure 6). As for the BubSub preview, the solver works on
``sign(contrast) * (data - background)``, so that non-negativity means "gas
attenuates less than liquid".
"""

from __future__ import annotations

import time

import numpy as np

from bubsub.core.metrics import projection_mse
from bubsub.clients.pipeline.static.preview import preview_grid
from bubsub.clients.pipeline.reconstruct import split_holdout
from bubsub.core.voxel import solvers
from bubsub.core.voxel.astra2d import AstraProjector2D, have_astra
from bubsub.core.voxel.projector3d import VoxelProjector

__all__ = ["voxel_baseline", "BB_ITERATIONS"]

#: Iterations of the paper's baseline.
BB_ITERATIONS = 30


def _operator(geometry, shape, extent):
    if geometry.ndim == 2:
        if have_astra():
            return AstraProjector2D(geometry, shape, extent)

    return VoxelProjector(geometry, shape, extent)


def voxel_baseline(scan, holdout, *, iterations=BB_ITERATIONS, shape=None, extent=None):
    """BB reconstruction of one (sub)scan and its held-out projection MSE.

    Parameters
    ----------
    scan : Scan
        One subscan as a static scan.
    holdout : {"odd", "even", None}
        Projections kept aside (as for BubSub).
    iterations : int
    shape, extent : optional
        The grid; default the BubSub preview grid.

    Returns
    -------
    dict
        ``image`` (bubbles positive, ``|contrast|`` inside), ``extent``,
        ``holdout_mse`` (None without a holdout), ``seconds``.
    """
    t0 = time.perf_counter()
    g_fit, d_fit, g_val, d_val = split_holdout(scan.geometry, scan.bubble_data, holdout)
    if shape is None:
        shape, extent = preview_grid(g_fit)
    sign = np.float32(np.sign(scan.bubble_contrast))
    op = _operator(g_fit, shape, extent)
    image = solvers.pgd_bb(op, sign * d_fit, iterations, nonneg=True)
    mse = None
    if g_val is not None:
        pred = sign * _operator(g_val, shape, extent).forward(image).reshape(g_val.shape)
        mse = projection_mse(pred, d_val)
    return {"image": image, "extent": tuple(extent), "holdout_mse": mse, "seconds": time.perf_counter() - t0}
