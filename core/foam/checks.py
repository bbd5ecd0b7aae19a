"""Argument checks and small constructors shared by the phantom generators (clear ValueErrors naming the argument)."""

from __future__ import annotations

import numbers

import numpy as np

from bubsub.core.projection.subdivision import icosphere

__all__ = ['unit_icosphere', 'rng_from_seed', 'count', 'finite', 'positive', 'nonneg', 'fraction', 'value_range', 'size_vector', 'frozen']


def unit_icosphere(subdivisions):
    """(vertices (n, 3) on the unit sphere, faces (m, 3) outward) of an icosphere (0..5 subdivisions)."""
    s = count("subdivisions", subdivisions, minimum=0)
    if s > 5:
        raise ValueError(f"subdivisions must be at most 5, got {s}")
    return icosphere(s)


def rng_from_seed(seed):
    if isinstance(seed, np.random.Generator):
        raise ValueError("seed must be an int (phantoms are reproducible from their seed), got a Generator")
    if seed is None or isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return np.random.default_rng(int(seed))


def count(name, value, minimum=1):
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def finite(name, value):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return v


def positive(name, value):
    v = finite(name, value)
    if v <= 0:
        raise ValueError(f"{name} must be positive, got {value!r}")
    return v


def nonneg(name, value):
    v = finite(name, value)
    if v < 0:
        raise ValueError(f"{name} must be non-negative, got {value!r}")
    return v


def fraction(name, value):
    v = finite(name, value)
    if not 0 <= v < 0.5:
        raise ValueError(f"{name} must be in [0, 0.5), got {value!r}")
    return v


def value_range(name, value):
    try:
        lo, hi = (float(x) for x in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair (min, max), got {value!r}") from None
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo <= hi):
        raise ValueError(f"{name} must satisfy 0 < min <= max, got {value!r}")
    return lo, hi


def size_vector(value, d):
    try:
        s = tuple(float(x) for x in np.broadcast_to(np.asarray(value, dtype=float), (d,)))
    except (TypeError, ValueError):
        raise ValueError(f"size must be a number or {d} numbers, got {value!r}") from None
    if not all(np.isfinite(x) and x > 0 for x in s):
        raise ValueError(f"size must be positive and finite, got {value!r}")
    return s


def frozen(a):
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a
