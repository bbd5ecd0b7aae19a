"""Stripe (ring artefact) removal on sinograms, with algotom's methods by Vo et al. (2018)."""

from __future__ import annotations

import numpy as np

__all__ = ["remove_stripes"]


def remove_stripes(sinogram, method="sort", *, size=21):
    """Remove stripes from one sinogram ``(n_angles, cols)`` of line integrals.

    Parameters
    ----------
    method : {"sort", "all"}
        ``sort``: algotom's ``remove_stripe_based_sorting`` (partial and
        full stripes); ``all``: ``remove_all_stripe`` (also wide and
        unresponsive stripes; slower).
    size : int
        Median filter size of the sorting method, pixels.

    Returns
    -------
    (n_angles, cols) float32
    """
    from algotom.prep.removal import remove_all_stripe, remove_stripe_based_sorting

    sino = np.asarray(sinogram, dtype=np.float32)
    if method == "sort":
        return np.asarray(remove_stripe_based_sorting(sino, size=size, dim=1), dtype=np.float32)
    if method == "all":
        return np.asarray(remove_all_stripe(sino, snr=3.0, la_size=51, sm_size=size), dtype=np.float32)
    raise ValueError(f"stripe method must be 'sort' or 'all', got {method!r}")
