"""Flat/dark correction and dead/hot pixel repair.

:func:`flat_model` averages the flats and darks of a region of interest
(streaming, a few frames at a time) into a
:class:`~bubsub.core.flatfield.FlatModel` (the flat-field correction that
scan files of raw counts share, :mod:`bubsub.core.flatfield`); its
:meth:`FlatModel.transmission` turns a slab of raw counts into intensity
transmissions ``(counts - dark) / (flat - dark)`` with one of three flat
choices:

* ``mean``: the mean of all flats;
* ``interp``: the flats taken before and after the scan are averaged
  separately and interpolated linearly in time (projection index) for each
  projection, which follows a beam that drifts or decays steadily;
* ``best``: the flats are averaged in groups and each projection takes the
  group whose pattern matches its open-beam (air) pixels best, scaled to
  their intensity, which follows beam fluctuations that are not monotonic.

Bad pixels (dead: no flat signal; hot: a dark far above its neighbours;
stuck: a flat far from its neighbours) are found once from the averaged
fields and replaced in every transmission by the median of their 3 x 3
neighbourhood.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from bubsub.core.flatfield import FlatModel, mean_flat_model, minus_log

__all__ = ["FlatModel", "flat_model", "mean_flat_model", "find_bad_pixels", "repair_pixels", "minus_log"]


def _stream_mean(source, which, start, stop, rows, cols, chunk=8):
    """Mean of frames ``start:stop``, read ``chunk`` at a time."""
    total = None
    for s in range(start, stop, chunk):
        block = source.read(which, slice(s, min(stop, s + chunk)), rows, cols).astype(np.float64)
        total = block.sum(axis=0) if total is None else total + block.sum(axis=0)
    return (total / (stop - start)).astype(np.float32)


def find_bad_pixels(flat, dark, *, tolerance=0.5, hot_sigma=10.0):
    """Dead, hot and stuck pixels from an averaged flat and dark.

    Parameters
    ----------
    flat, dark : (rows, cols) float
    tolerance : float
        A pixel whose flat signal differs from the median of its 3 x 3
        neighbourhood by more than this fraction is bad.
    hot_sigma : float
        Darks more than this many robust standard deviations above the
        median dark are hot.

    Returns
    -------
    (rows, cols) bool
    """
    span = flat - dark
    size = (3, 3) if min(span.shape) >= 3 else (1, 3)
    local = ndimage.median_filter(span, size=size, mode="nearest")
    ref = np.maximum(local, 1e-6)
    bad = (span <= 0.05 * np.median(span)) | (np.abs(span / ref - 1) > tolerance)
    med = np.median(dark)
    mad = 1.4826 * np.median(np.abs(dark - med))
    bad |= dark > med + hot_sigma * max(mad, 1.0)
    return bad


def repair_pixels(images, bad):
    """Replace the bad pixels of each image by the median of their 3 x 3 neighbourhood (in place)."""
    if not bad.any():
        return images
    size = (3, 3) if min(bad.shape) >= 3 else (1, 3)
    for img in images:
        img[bad] = ndimage.median_filter(img, size=size, mode="nearest")[bad]
    return images


def flat_model(source, rows, cols, *, mode="interp", no_flat=False, flats_before=None, repair=True,
               groups=8, air_threshold=0.9, n_projections=None):
    """Average the flats and darks of a ROI into a :class:`FlatModel`.

    Parameters
    ----------
    source : RawSource
    rows, cols : (int, int)
        ROI in raw detector pixels.
    mode : {"mean", "interp", "best"}
    no_flat : bool
        Proceed without flats (each projection is normalised by its
        brightest level); missing darks are then taken as 0.
    flats_before : int, optional
        How many of the flats (in file order) were taken before the scan;
        default half of them (``interp``).
    repair : bool
        Find bad pixels (else the map is empty).
    groups : int
        Flat groups for ``best``.
    air_threshold : float
        Pixels whose transmission in the first projection exceeds this are
        open beam (``best``).

    Raises
    ------
    ValueError
        If flats or darks are missing and ``no_flat`` is not set, or
        ``best`` finds no open-beam pixels.
    """
    shape = (rows[1] - rows[0], cols[1] - cols[0])
    missing = [w for w, n in (("flats (/exchange/data_white)", source.n_flats),
                              ("darks (/exchange/data_dark)", source.n_darks)) if n == 0]
    if missing and not no_flat:
        raise ValueError(f"{source.path.name} has no {' and no '.join(missing)}; they are needed for the flat-field "
                         f"correction. Pass --no-flat to normalise each projection by its open-beam level instead")
    dark = _stream_mean(source, "dark", 0, source.n_darks, rows, cols) if source.n_darks else np.zeros(shape, np.float32)
    if no_flat or source.n_flats == 0:
        flat = np.full(shape, np.nan, np.float32)
        bad = np.zeros(shape, bool)
        if repair:
            med = np.median(dark)
            bad = dark > med + 10 * max(1.4826 * np.median(np.abs(dark - med)), 1.0)
        return FlatModel("none", dark, flat[None], np.zeros(1), bad)
    nf = source.n_flats
    if mode == "interp":
        nb = nf // 2 if flats_before is None else flats_before
        if not 0 < nb < nf:
            raise ValueError(f"--flat interp needs flats before and after the scan; {nb} of the {nf} flats are "
                             f"before (set --flats-before, or use --flat mean)")
        before = _mean_range(source, 0, nb, rows, cols)
        after = _mean_range(source, nb, nf, rows, cols)
        n = source.n_projections if n_projections is None else n_projections
        flats, times = np.stack([before, after]), np.array([-0.5, n - 0.5])
    elif mode == "best":
        g = max(1, min(groups, nf))
        edges = np.linspace(0, nf, g + 1).round().astype(int)
        flats = np.stack([_mean_range(source, a, b, rows, cols) for a, b in zip(edges[:-1], edges[1:])])
        times = 0.5 * (edges[:-1] + edges[1:])
    else:
        flats, times = _mean_range(source, 0, nf, rows, cols)[None], np.zeros(1)
    mean_flat = flats.mean(axis=0)
    bad = find_bad_pixels(mean_flat, dark) if repair else np.zeros(shape, bool)
    air = None
    if mode == "best":
        first = source.read("data", slice(0, 1), rows, cols)[0]
        t = (first - dark) / np.maximum(mean_flat - dark, 1e-6)
        air = (t > air_threshold) & ~bad
        if air.sum() < max(16, 0.005 * air.size):
            raise ValueError("--flat best needs open-beam pixels (transmission > 0.9) beside the sample to match "
                             "flats; none in this ROI: use --flat interp or mean")
    return FlatModel(mode, dark, flats.astype(np.float32), times, bad, air)


def _mean_range(source, a, b, rows, cols):
    return _stream_mean(source, "white", a, b, rows, cols)
