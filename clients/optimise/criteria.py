"""Model choice: the Akaike criterion of a projection fit, so that extra unknowns must earn their place."""

from __future__ import annotations

import numpy as np

__all__ = ["akaike_score"]


def akaike_score(objective, m, k):
    """``m log(2 f / m) + 2 k``: the Akaike criterion of a least-squares fit (lower is better).

    Parameters
    ----------
    objective : float
        ``f = 0.5 ||Proj(S x) - d||^2`` at the fitted ``x``.
    m : int
        Number of data values (detector pixels times projections).
    k : int
        Number of unknowns (control vertex coordinates of all bubbles).

    Notes
    -----
    With Gaussian noise of unknown variance ``sigma^2``, estimated as
    ``2 f / m``, the log-likelihood is ``-m/2 log(2 f / m)`` up to a
    constant; two models are compared by this score minus twice the
    log-likelihood plus twice the unknowns.
    """
    return float(m) * float(np.log(max(2.0 * float(objective) / float(m), 1e-300))) + 2.0 * float(k)
