"""Checks of arguments shared by the stages: one message for each kind of bad value."""

from __future__ import annotations

import numbers

__all__ = ["check_int"]


def check_int(value, name, minimum=0, maximum=None):
    """``value`` as an int, or a ValueError naming ``name`` unless it is an integer in ``minimum..maximum``.

    Booleans are refused (``True`` is an ``int`` to Python, never a count to bubsub); numpy
    integers are accepted.

    Parameters
    ----------
    value : object
    name : str
        How the message calls it (``"iterations"``, ``"--slabs"``).
    minimum : int
        0 for a count that may be zero, 1 for a positive one.
    maximum : int, optional
        The largest value allowed; None for no bound.

    Returns
    -------
    int

    Raises
    ------
    ValueError
    """
    bad = isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum
    if not bad and maximum is not None and value > maximum:
        bad = True
    if bad:
        if maximum is not None:
            kind = f"an integer in {minimum}..{maximum}"
        else:
            kind = {0: "a non-negative integer", 1: "a positive integer"}.get(minimum, f"an integer >= {minimum}")
        raise ValueError(f"{name} must be {kind}, got {value!r}")
    return int(value)
