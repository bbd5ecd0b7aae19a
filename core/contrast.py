"""The bubble contrast's sign checked against the data: one check for ``bubsub prepare`` and ``bubsub reconstruct``.

Gas bubbles attenuate less than the liquid, so the bubble contrast
(gas minus liquid, 1/mm) is negative and ``data - background`` is negative
where a bubble is and noise elsewhere. A contrast whose sign disagrees with
the data makes every fit meaningless, so both commands refuse it before any
computation.
"""

from __future__ import annotations

import numpy as np

__all__ = ["signal_masses", "contrast_sign_error"]


def signal_masses(bubble_data, noise=0.0):
    """The positive and negative mass of ``data - background`` beyond the noise.

    Parameters
    ----------
    bubble_data : array_like
        ``data - background``, any shape.
    noise : float
        Values within ``+-noise`` count as noise (``prepare`` uses 3 sigma of
        the noise; 0 counts every value).

    Returns
    -------
    positive, negative : float
        ``sum(max(x - noise, 0))`` and ``sum(max(-x - noise, 0))``, float64 sums.
    """
    x = np.asarray(bubble_data)
    noise = float(noise)
    pos = float(np.sum(x - noise, where=x > noise, dtype=np.float64))
    neg = float(np.sum(-x - noise, where=x < -noise, dtype=np.float64))
    return pos, neg


def contrast_sign_error(contrast, bubble_data, *, noise=0.0):
    """Why the sign of ``contrast`` disagrees with the data, or None when it agrees.

    Parameters
    ----------
    contrast : float
        Bubble contrast, gas minus liquid (1/mm).
    bubble_data : array_like
        ``data - background``.
    noise : float
        See :func:`signal_masses`.

    Returns
    -------
    str or None
        A sentence naming the contrast and which way the data lean; the
        caller adds what to do (the flag or attribute to correct). Also a
        message when the data hold no signal beyond the noise.
    """
    pos, neg = signal_masses(bubble_data, noise)
    if pos == 0 and neg == 0:
        return "data - background is zero everywhere (within the noise): there is no bubble signal"
    lean = -1.0 if neg > pos else 1.0
    if np.sign(contrast) == lean:
        return None
    return (f"the bubble contrast {contrast:+.4g} 1/mm disagrees with the data (wrong sign): data - background is "
            f"mostly {'negative' if lean < 0 else 'positive'}, so the bubbles {'lower' if lean < 0 else 'raise'} the "
            f"line integrals (gas bubbles lower them, with a negative contrast)")
