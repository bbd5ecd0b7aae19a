"""Offsets of whole projections in ``-log``: what a flat field that follows the beam's decay imperfectly adds,
removed from the air beside the sample (:func:`air_offsets`) or, with no air, as a slow drift
(:func:`drift_offsets`)."""

from __future__ import annotations

import numpy as np

__all__ = ["air_offsets", "drift_offsets", "AIR_LEVEL", "AIR_FRACTION", "AIR_COLUMNS"]


#: A row has air beside its sample where its background's least value is below this fraction of its peak ...
AIR_LEVEL = 0.1
#: ... and its air columns are those within this fraction of the background's range of that least value.
AIR_FRACTION = 0.02
#: Least number of air columns in a row for :func:`air_offsets` to act on it.
AIR_COLUMNS = 4


def air_offsets(block, background, found=None):
    """Subtract from each projection's row its offset in air, in place; whether any row had air.

    A flat field interpolated between the flats taken before and after the
    scan follows the beam's decay and drift only approximately, which
    offsets whole projections by a few hundredths in ``-log`` (negative line
    integrals in air, a drift that the fit would take for gas). Where a row
    has air beside the sample (its background's least value below
    :data:`AIR_LEVEL` of its peak, and at least :data:`AIR_COLUMNS` columns
    within :data:`AIR_FRACTION` of its range of it), each projection's
    median of ``data - background`` there is its offset. A sample wider than
    the detector (no air) is left as it is.

    Parameters
    ----------
    block : (n_angles, rows, cols) float
        Line integrals; corrected in place.
    background : (n_angles, rows, cols) or broadcastable float
        Its background.
    found : list, optional
        Each corrected row's ``(n_angles,)`` offsets are appended.

    Returns
    -------
    bool
    """
    bg = np.broadcast_to(background, block.shape)
    done = False
    for r in range(block.shape[1]):
        level = bg[:, r].max(axis=0)
        low, peak = float(level.min()), float(level.max())
        if peak <= 0 or low > AIR_LEVEL * peak:  # no air in this row (a sample wider than the detector)
            continue
        air = level <= low + AIR_FRACTION * (peak - low)
        if np.count_nonzero(air) < AIR_COLUMNS:
            continue
        off = np.median((block[:, r] - bg[:, r])[:, air], axis=1)
        block[:, r] -= off[:, None]
        if found is not None:
            found.append(off)
        done = True
    return done


def drift_offsets(sino, background):
    """Remove a slow drift of whole projections from a row with no air, in place; returns its range.

    Without air beside the sample (:func:`air_offsets` cannot act) the
    offset a flat field that follows the beam's decay imperfectly adds to
    each projection is estimated from the bubbles' signal itself: a foam
    filling a rotation-invariant liquid sends about the same amount of gas
    through the detector at every angle, so the mean of ``data -
    background`` over the columns varies with the angle only by the
    bubbles' chance arrangement, not by a trend. A quadratic over the
    projection index fitted to that mean is the drift; it is subtracted,
    its mean kept (the mean is the gas, not a drift).

    Parameters
    ----------
    sino : (n_angles, cols) float
        One row's line integrals; corrected in place.
    background : (n_angles, cols) or (cols,) float

    Returns
    -------
    float
        The drift's range over the projections (``-log`` units).
    """
    n = sino.shape[0]
    if n < 8:
        return 0.0
    x = np.linspace(-1.0, 1.0, n)
    mean = (sino - background).mean(axis=1)
    drift = np.polynomial.polynomial.polyval(x, np.polynomial.polynomial.polyfit(x, mean, 2))
    drift -= drift.mean()
    sino -= drift[:, None].astype(sino.dtype)
    return float(np.ptp(drift))
