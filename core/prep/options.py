"""What ``bubsub prepare`` can be told, validated before any heavy work.

:class:`PrepareOptions` is immutable; :func:`prepare_options` builds one
from keyword arguments (or the command line's strings), checks every value
and says what is wrong. The checks that need the raw file (ROI inside the
detector, binning dividing the ROI, projections in range) are in
:func:`check_against_raw`.
"""

from __future__ import annotations

import dataclasses
import numbers
from pathlib import Path

import numpy as np

from bubsub.core.validate import check_int

__all__ = ["PrepareOptions", "prepare_options", "parse_roi", "parse_projections", "check_against_raw",
           "FLAT_MODES", "STRIPE_METHODS", "DOUBLE_FLAT", "CENTER_METHODS", "parse_quantity"]

#: Flat-field choices: the mean of all flats, linear interpolation in time between the flats
#: taken before and after the scan, or the best-matching flat (group mean) per projection.
FLAT_MODES = ("mean", "interp", "best")
#: Stripe/ring removal (algotom): sorting-based, or algotom's combined "all stripes" method.
STRIPE_METHODS = ("none", "sort", "all")
#: Pixel gains the flats do not show, from the mean of the projections, divided out before phase retrieval
#: (:mod:`bubsub.core.prep.gains`): ``auto`` on a sample wider than the detector with phase retrieval.
DOUBLE_FLAT = ("auto", "on", "off")
#: Rotation-centre search: Vo's Fourier method (algotom) on the middle sinogram, or the 0/180-degree pair.
CENTER_METHODS = ("auto", "vo", "pair", "none")


@dataclasses.dataclass(frozen=True)
class PrepareOptions:
    """Settings of one preparation (lengths in mm, energy in keV, columns in raw detector pixels).

    ``roi`` is ``((row0, row1), (col0, col1))`` in raw detector pixels (end
    exclusive, ``None`` = to the edge); ``projections`` is ``(start, stop,
    step)``; ``center`` is ``"auto"``, ``"vo"``, ``"pair"``, ``"none"`` or
    a raw-detector column (float); ``background`` is ``"auto"``,
    ``"envelope"``, ``"reproject"``, ``"none"`` or a file path;
    ``liquid_radius`` is the radius of a liquid cylinder wider than the
    detector (the container's inner radius), which ``background="auto"``
    then takes instead of fitting it (:func:`bubsub.core.prep.background.chord_background`).
    """

    flat: str = "interp"
    no_flat: bool = False
    flats_before: int | None = None
    repair_pixels: bool = True
    stripes: str = "none"
    double_flat: str = "auto"
    delta_beta: float | None = None
    energy: float | None = None
    distance: float | None = None
    pixel_size: float | None = None
    roi: tuple = ((None, None), (None, None))
    bin: int = 1
    projections: tuple = (None, None, 1)
    center: object = "auto"
    crop_to_axis: bool = True
    background: object = "auto"
    foam_radius: float | None = None
    liquid_radius: float | None = None
    contrast: float | None = None
    source_origin: float | None = None
    origin_detector: float | None = None
    theta_units: str | None = None
    slab_mb: float = 256.0
    min_transmission: float = 1e-3

    def __repr__(self):
        fields = ", ".join(f"{f.name}={getattr(self, f.name)!r}" for f in dataclasses.fields(self)
                           if getattr(self, f.name) != f.default)
        return f"prepare_options({fields})"

    def as_dict(self):
        """Plain values for ``report.json``."""
        return {f.name: (str(v) if isinstance(v := getattr(self, f.name), Path) else v)
                for f in dataclasses.fields(self)}


def _positive(name, value, *, allow_none=True):
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not value > 0 or value != value:
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return float(value)


def parse_roi(text):
    """``"ROW0:ROW1,COL0:COL1"`` (either part may be ``:``) -> ``((row0, row1), (col0, col1))``.

    Raises
    ------
    ValueError
        If the text is not two ``A:B`` ranges of non-negative integers with ``A < B``.
    """
    if not isinstance(text, str):
        return _roi_tuple(text)
    parts = text.split(",")
    if len(parts) != 2:
        raise ValueError(f"--roi must be ROW0:ROW1,COL0:COL1 (e.g. 100:900,8:2008), got {text!r}")
    out = []
    for axis, part in zip(("rows", "columns"), parts):
        bounds = part.split(":")
        if len(bounds) != 2:
            raise ValueError(f"--roi {axis} must be A:B, got {part!r} in {text!r}")
        try:
            lo, hi = (int(b) if b.strip() else None for b in bounds)
        except ValueError:
            raise ValueError(f"--roi {axis} bounds must be integers (pixels), got {part!r}") from None
        out.append((lo, hi))
    return _roi_tuple(tuple(out))


def _roi_tuple(roi):
    try:
        (r0, r1), (c0, c1) = roi
    except (TypeError, ValueError):
        raise ValueError(f"roi must be ((row0, row1), (col0, col1)), got {roi!r}") from None
    for axis, lo, hi in (("rows", r0, r1), ("columns", c0, c1)):
        for b in (lo, hi):
            if b is not None and (isinstance(b, bool) or not isinstance(b, numbers.Integral) or b < 0):
                raise ValueError(f"roi {axis} bounds must be non-negative integers, got {b!r}")
        if lo is not None and hi is not None and not lo < hi:
            raise ValueError(f"roi {axis} range {lo}:{hi} is empty (the end is exclusive)")
    return ((r0, r1), (c0, c1))


def parse_projections(text):
    """``"A:B:STEP"`` (parts may be empty) -> ``(start, stop, step)``."""
    if not isinstance(text, str):
        start, stop, step = text
    else:
        bits = text.split(":")
        if not 1 <= len(bits) <= 3:
            raise ValueError(f"--projections must be START:STOP:STEP, got {text!r}")
        try:
            vals = [int(b) if b.strip() else None for b in bits] + [None] * (3 - len(bits))
        except ValueError:
            raise ValueError(f"--projections parts must be integers, got {text!r}") from None
        start, stop, step = vals
    step = 1 if step is None else step
    check_int(step, "projection step", 1)
    for b in (start, stop):
        if b is not None and (not isinstance(b, numbers.Integral) or b < 0):
            raise ValueError(f"projection bounds must be non-negative integers, got {b!r}")
    return (start, stop, int(step))


def prepare_options(**kw):
    """Validated :class:`PrepareOptions` (strings from the command line are parsed here).

    Raises
    ------
    ValueError
        Naming the first bad setting.
    """
    unknown = set(kw) - {f.name for f in dataclasses.fields(PrepareOptions)}
    if unknown:
        raise ValueError(f"unknown prepare option(s) {sorted(unknown)}")
    o = dict(kw)
    if o.get("flat", "interp") not in FLAT_MODES:
        raise ValueError(f"flat must be one of {FLAT_MODES}, got {o['flat']!r}")
    if o.get("stripes", "none") not in STRIPE_METHODS:
        raise ValueError(f"stripes must be one of {STRIPE_METHODS}, got {o['stripes']!r}")
    if o.get("double_flat", "auto") not in DOUBLE_FLAT:
        raise ValueError(f"double_flat must be one of {DOUBLE_FLAT}, got {o['double_flat']!r}")
    for name in ("delta_beta", "energy", "distance", "pixel_size", "foam_radius", "liquid_radius", "source_origin",
                 "origin_detector"):
        if name in o:
            o[name] = _positive(name, o[name])
    if o.get("theta_units") not in (None, "deg", "rad"):
        raise ValueError(f"theta_units must be 'deg' or 'rad', got {o['theta_units']!r}")
    o["slab_mb"] = _positive("slab_mb", o.get("slab_mb", 256.0), allow_none=False)
    mt = o.get("min_transmission", 1e-3)
    if not isinstance(mt, numbers.Real) or not 0 < mt < 1:
        raise ValueError(f"min_transmission must be in (0, 1), got {mt!r}")
    if (o.get("source_origin") is None) != (o.get("origin_detector") is None):
        raise ValueError("a cone beam needs both source_origin and origin_detector (mm)")
    if "roi" in o:
        o["roi"] = parse_roi(o["roi"]) if o["roi"] is not None else ((None, None), (None, None))
    if "projections" in o:
        o["projections"] = parse_projections(o["projections"]) if o["projections"] is not None else (None, None, 1)
    b = o.get("bin", 1)
    check_int(b, "bin", 1)
    fb = o.get("flats_before")
    if fb is not None:
        check_int(fb, "flats_before", 0)
    o["center"] = _center(o.get("center", "auto"))
    o["background"] = _background(o.get("background", "auto"))
    c = o.get("contrast")
    if c is not None:
        if isinstance(c, bool) or not isinstance(c, numbers.Real) or c != c or c == 0:
            raise ValueError(f"contrast must be a non-zero number (gas minus liquid attenuation, 1/mm), got {c!r}")
        o["contrast"] = float(c)
    return PrepareOptions(**o)


def _center(value):
    if isinstance(value, str):
        if value in CENTER_METHODS:
            return value
        try:
            value = float(value)
        except ValueError:
            raise ValueError(f"center must be one of {CENTER_METHODS} or a detector column, got {value!r}") from None
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or value != value:
        raise ValueError(f"center must be one of {CENTER_METHODS} or a detector column, got {value!r}")
    return float(value)


def _background(value):
    if value in ("auto", "envelope", "reproject", "none"):
        return value
    p = Path(value)
    if not p.is_file():
        raise ValueError(f"background must be auto, envelope, reproject, none or an existing file; "
                         f"{str(p)!r} is not a file")
    return p


def check_against_raw(options, det_shape, n_projections):
    """The ROI, binning and projection range resolved against the raw detector.

    Parameters
    ----------
    options : PrepareOptions
    det_shape : (rows, cols) int
        Raw detector shape.
    n_projections : int

    Returns
    -------
    rows : (int, int)
    cols : (int, int)
    index : (k,) int array
        Selected projection indices.

    Raises
    ------
    ValueError
        If the ROI leaves the detector, the binning does not divide the ROI,
        or the projection range selects nothing.
    """
    rows, cols = det_shape
    (r0, r1), (c0, c1) = options.roi
    r0, r1 = 0 if r0 is None else r0, rows if r1 is None else r1
    c0, c1 = 0 if c0 is None else c0, cols if c1 is None else c1
    if r1 > rows or c1 > cols or r0 >= r1 or c0 >= c1:
        raise ValueError(f"ROI rows {r0}:{r1}, columns {c0}:{c1} lies outside the detector of "
                         f"{rows} rows x {cols} columns")
    k = options.bin
    for axis, n in (("rows", r1 - r0), ("columns", c1 - c0)):
        if n % k and not (axis == "rows" and n == 1):
            raise ValueError(f"--bin {k} does not divide the {n} ROI {axis}; choose a ROI whose size is a "
                             f"multiple of {k}")
    start, stop, step = options.projections
    if start is not None and start >= n_projections:
        raise ValueError(f"projection start {start} is beyond the {n_projections} projections")
    index = np.arange(n_projections)[slice(start, stop, step)]
    if index.size < 2:
        raise ValueError(f"projections {start}:{stop}:{step} select {index.size} of {n_projections}; need at least 2")
    return (r0, r1), (c0, c1), index


_QUANTITY_UNITS = {
    "energy": ({"kev": 1.0, "ev": 1e-3, "mev": 1e3}, "keV"),
    "length": ({"mm": 1.0, "um": 1e-3, "µm": 1e-3, "nm": 1e-6, "cm": 10.0, "m": 1e3}, "mm"),
}


def parse_quantity(text, kind, *, name):
    """``"3um"``, ``"0.003mm"``, ``"25 cm"``, ``"16keV"`` -> float in mm or keV.

    A bare number is read in the project's units (mm, keV).

    Raises
    ------
    ValueError
        For an unknown unit or a non-positive value.
    """
    import re

    if isinstance(text, (int, float)) and not isinstance(text, bool):
        return _positive(name, float(text), allow_none=False)
    m = re.fullmatch(r"\s*([-+0-9.eE]+)\s*([A-Za-zµ]*)\s*", str(text))
    table, default = _QUANTITY_UNITS[kind]
    if not m:
        raise ValueError(f"{name} must be a number with an optional unit ({', '.join(table)}), got {text!r}")
    try:
        value = float(m.group(1))
    except ValueError:
        raise ValueError(f"{name} must be a number with an optional unit, got {text!r}") from None
    unit = m.group(2).lower() or default.lower()
    if unit not in table:
        raise ValueError(f"{name}: unknown unit {m.group(2)!r} in {text!r}; use one of {', '.join(table)}")
    return _positive(name, value * table[unit], allow_none=False)
