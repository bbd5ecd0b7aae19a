"""Detector pixel gains that the flats do not show, taken from the projections themselves (a double flat-field).

A pixel whose gain differs between the flats and the projections (a stripe
in the sinogram, a ring in a reconstruction) multiplies every projection's
transmission by the same factor. In ``-log`` that is one constant per pixel,
the same in every view, which a foam wider than the detector's fit takes in
its view-constant term (:mod:`bubsub.clients.pipeline.static.detector_term`).
Paganin's filter, though, acts on the transmission before the ``-log``: it
spreads the factor over the neighbouring columns weighted by each view's
intensity there, phase-contrast fringes included, and what comes out
differs from view to view; the fit then explains it with spikes of the
bubbles that cross the ring. Dividing the gains out of the transmission
before the retrieval leaves nothing for it to spread.

The gains are the fine part of the mean over all projections of the log
transmission: the sample's mean projection is smooth at the scale of a few
columns (a rotating sample's features move from view to view), a pixel's
gain error is not. Each row's mean is compared with its running median over
:data:`GAIN_MEDIAN_COLUMNS` columns; what stands out is the gain.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import median_filter

__all__ = ["GAIN_MEDIAN_COLUMNS", "stripe_gains"]

#: Columns of the running median that stands for the sample's smooth mean projection: gain errors narrower
#: than half of it are found.
GAIN_MEDIAN_COLUMNS = 9


def stripe_gains(mean_log, width=GAIN_MEDIAN_COLUMNS):
    """Each pixel's gain from the mean over the projections of the log transmission.

    Parameters
    ----------
    mean_log : ndarray, ``(rows, cols)``
        Mean over all projections of ``log`` of the flat-corrected transmission.
    width : int
        Columns of the running median along each row (odd, at least 3).

    Returns
    -------
    ndarray float32, ``(rows, cols)``
        The factor each pixel's transmission carries: divide it out before phase retrieval.
    """
    mean_log = np.asarray(mean_log, dtype=np.float64)
    if mean_log.ndim != 2:
        raise ValueError(f"mean_log must be (rows, cols), got shape {mean_log.shape}")
    if not isinstance(width, (int, np.integer)) or width < 3 or width % 2 == 0:
        raise ValueError(f"width must be an odd number of columns >= 3, got {width!r}")
    # continued beyond each end by point reflection, so that a sloped mean (a liquid's chord near the detector's
    # side) stays its own running median up to the last column
    h = min(int(width) // 2, mean_log.shape[1] - 1)
    left = 2 * mean_log[:, :1] - mean_log[:, h:0:-1]
    right = 2 * mean_log[:, -1:] - mean_log[:, -2:-2 - h:-1]
    padded = np.concatenate([left, mean_log, right], axis=1)
    smooth = median_filter(padded, size=(1, int(width)), mode="nearest")[:, h:h + mean_log.shape[1]]
    return np.exp(mean_log - smooth).astype(np.float32)
