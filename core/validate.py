"""Checks of arguments shared by the stages: one message for each kind of bad value."""

from __future__ import annotations

import numbers

__all__ = ["check_int"]


def check_int(value, name, minimum=0):
    """``value`` as an int, or a ValueError naming ``name`` unless it is an integer >= ``minimum``.

    Booleans are refused (``True`` is an ``int`` to Python, never a count to bubsub); numpy
    integers are accepted.

    Parameters
    ----------
    value : object
    name : str
        How the message calls it (``"iterations"``, ``"--slabs"``).
    minimum : int
        0 for a count that may be zero, 1 for a positive one.

    Returns
    -------
    int

    Raises
    ------
    ValueError
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        kind = {0: "a non-negative integer", 1: "a positive integer"}.get(minimum, f"an integer >= {minimum}")
        raise ValueError(f"{name} must be {kind}, got {value!r}")
    return int(value)
