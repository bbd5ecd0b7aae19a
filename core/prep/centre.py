"""Rotation-axis search for parallel-beam scans.

* :func:`center_vo`: Vo et al. (2014)'s Fourier method on a 180-degree
  sinogram, as implemented by algotom (``find_center_vo``).
* :func:`center_pair`: a projection and its mirror image taken 180 degrees
  later are reflections of each other about the axis; their registration
  shift (scikit-image's sub-pixel phase correlation) gives the axis column.

Columns are detector pixel indices (pixel ``j`` has its centre at ``j``),
so the axis of a centred detector is at ``(cols - 1) / 2``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["center_vo", "center_pair", "closest_pair"]


def center_vo(sinogram):
    """Axis column of a 180-degree sinogram ``(n_angles, cols)`` of line integrals (algotom)."""
    from algotom.prep.calculation import find_center_vo

    sino = np.asarray(sinogram, dtype=np.float32)
    if sino.ndim != 2 or sino.shape[0] < 8:
        raise ValueError(f"the centre search needs a (n_angles >= 8, cols) sinogram, got shape {sino.shape}")
    cols = sino.shape[1]
    # search the middle half of the detector (algotom's default is the middle eighth)
    return float(find_center_vo(sino, start=cols * 0.25, stop=cols * 0.75, step=0.25, ncore=1))


def closest_pair(theta_deg):
    """The two projections whose angles differ by the closest to 180 degrees.

    Returns
    -------
    i, j : int
    error : float
        ``|theta[j] - theta[i] - 180|``, degrees.
    """
    t = np.asarray(theta_deg, dtype=float)
    diff = np.abs(np.abs(t[None, :] - t[:, None]) - 180.0)
    i, j = np.unravel_index(np.argmin(diff), diff.shape)
    i, j = (i, j) if t[i] < t[j] else (j, i)
    return int(i), int(j), float(diff[i, j])


def center_pair(p0, p180):
    """Axis column from two projections 180 degrees apart.

    Parameters
    ----------
    p0, p180 : (rows, cols) or (cols,) float
        Line integrals (flat-corrected, ``-log``).

    Returns
    -------
    float
        Axis column (pixel index units).
    """
    from skimage.registration import phase_cross_correlation

    a, b = np.atleast_2d(np.asarray(p0, dtype=float)), np.atleast_2d(np.asarray(p180, dtype=float))
    if a.shape != b.shape:
        raise ValueError(f"the two projections differ in shape: {a.shape} and {b.shape}")
    # a feature at column c + s in p0 sits at c - s in p180, i.e. at cols - 1 - c + s once p180 is mirrored
    shift, _, _ = phase_cross_correlation(a, b[:, ::-1], upsample_factor=20, normalization=None)
    return 0.5 * (a.shape[1] - 1 + float(shift[-1]))
