"""Dynamic scans: one scan file, all projections in acquisition order, cut into subscans.

A dynamic scan is a :class:`~bubsub.core.io.scanfile.Scan` whose projections
``k * K .. (k + 1) * K - 1`` form subscan ``k`` (``K = projections_per_subscan``,
the root attribute of the file or given by the user). :func:`subscan_layout`
checks the numbers once; :func:`subscan` cuts one subscan out as a static
scan that :func:`bubsub.clients.pipeline.reconstruct.reconstruct` accepts.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from bubsub.core.io.scanfile import Scan
from bubsub.core.validate import check_int

__all__ = ["SubscanLayout", "subscan_layout", "parse_subscan_range", "subscan", "subscan_times"]


@dataclasses.dataclass(frozen=True)
class SubscanLayout:
    """How a dynamic scan's projections split into subscans.

    Attributes
    ----------
    per_subscan : int
        Projections per subscan.
    n_subscans : int
        Complete subscans in the scan.
    selected : range
        The subscans to reconstruct (a sub-range of ``range(n_subscans)``).
    leftover : int
        Trailing projections that make no complete subscan (ignored).
    """

    per_subscan: int
    n_subscans: int
    selected: range
    leftover: int = 0

    def projections(self, index):
        """Projection indices of subscan ``index``: a slice."""
        if not 0 <= index < self.n_subscans:
            raise ValueError(f"subscan {index} is out of range: the scan has subscans 0..{self.n_subscans - 1}")
        return slice(index * self.per_subscan, (index + 1) * self.per_subscan)

    def __repr__(self):
        return (f"subscan_layout(per_subscan={self.per_subscan}, n_subscans={self.n_subscans}, "
                f"selected=range({self.selected.start}, {self.selected.stop}), leftover={self.leftover})")


def parse_subscan_range(text, n_subscans):
    """``"A:B"`` (python slice, ends optional, negatives count from the end) or ``"A"`` -> range.

    Raises
    ------
    ValueError
        If the text is not ``A:B`` / ``A`` with integers, or selects a subscan
        outside ``0..n_subscans-1`` or none at all.
    """
    if isinstance(text, range):
        lo, hi = text.start, text.stop
    else:
        parts = str(text).split(":")
        if len(parts) > 2:
            raise ValueError(f"subscan range {text!r} must be A:B or A")
        try:
            vals = [int(x) if x.strip() else None for x in parts]
        except ValueError:
            raise ValueError(f"subscan range {text!r} must be A:B or A with integers") from None
        if len(vals) == 1:
            if vals[0] is None:
                raise ValueError("subscan range is empty")
            lo, hi = vals[0], (vals[0] + 1 if vals[0] != -1 else None)
        else:
            lo, hi = vals
    lo = 0 if lo is None else lo
    hi = n_subscans if hi is None else hi
    lo_abs = lo + n_subscans if lo < 0 else lo
    hi_abs = hi + n_subscans if hi < 0 else hi
    if not 0 <= lo_abs < n_subscans or not 0 < hi_abs <= n_subscans:
        raise ValueError(f"subscan range {text!r} is out of bounds: the scan has subscans 0..{n_subscans - 1} "
                         f"(A:B selects A..B-1)")
    if hi_abs <= lo_abs:
        raise ValueError(f"subscan range {text!r} selects no subscan")
    return range(lo_abs, hi_abs)


def subscan_layout(scan, projections_per_subscan=None, subscans=None, *, incomplete="drop"):
    """Check and describe a dynamic scan's subscans.

    Parameters
    ----------
    scan : Scan
    projections_per_subscan : int, optional
        Overrides (or supplies) ``scan.projections_per_subscan``; a value that
        contradicts the file's attribute is an error.
    subscans : str or range, optional
        ``"A:B"`` (see :func:`parse_subscan_range`); default all.
    incomplete : {"drop", "error"}
        Projections after the last complete subscan: ignored with a warning,
        or refused.

    Returns
    -------
    SubscanLayout
    """
    if not isinstance(scan, Scan):
        raise ValueError(f"scan must be a Scan, got {type(scan).__name__}")
    k = projections_per_subscan
    if k is not None:
        check_int(k, "projections_per_subscan", 1)
    stored = scan.projections_per_subscan
    if k is not None and stored is not None and int(k) != stored:
        raise ValueError(f"projections_per_subscan {k} contradicts the scan file's attribute "
                         f"projections_per_subscan = {stored}; leave it out to use the file's")
    k = int(k) if k is not None else stored
    if k is None:
        raise ValueError("the scan file has no root attribute 'projections_per_subscan'; "
                         "give --projections-per-subscan")
    n = scan.n_angles
    if k > n:
        raise ValueError(f"projections_per_subscan = {k} exceeds the scan's {n} projections")
    n_sub, rest = divmod(n, k)
    if rest:
        msg = (f"projections_per_subscan = {k} does not divide the scan's {n} projections: "
               f"{n_sub} complete subscans, the last {rest} projections are ignored")
        if incomplete == "error":
            raise ValueError(msg)
        if incomplete != "drop":
            raise ValueError(f"incomplete must be 'drop' or 'error', got {incomplete!r}")
        warnings.warn(msg, stacklevel=2)
    selected = parse_subscan_range(subscans if subscans is not None else ":", n_sub)
    return SubscanLayout(k, n_sub, selected, rest)


def subscan(scan, layout, index):
    """Subscan ``index`` of a dynamic scan as a static :class:`Scan` (attrs ``subscan`` set)."""
    out = scan.subset(layout.projections(index))
    out.attrs["subscan"] = int(index)
    return out


def subscan_times(scan, layout):
    """Mid-time of every subscan: ``(n_subscans,) float`` and its unit.

    The mean of the projections' ``/exchange/time`` (seconds), or the
    subscan index (unit ``"subscan"``) when the scan has no times.
    """
    if scan.time is None:
        return np.arange(layout.n_subscans, dtype=float), "subscan"
    t = scan.time[: layout.n_subscans * layout.per_subscan].reshape(layout.n_subscans, layout.per_subscan)
    return t.mean(axis=1), "s"
