"""The flat-field correction: raw counts to intensity transmissions, and transmissions to line integrals.

:class:`FlatModel` holds averaged flats and darks (one group, or several
groups in time) and a bad-pixel map; :meth:`FlatModel.transmission` divides
a slab of raw counts by them, and :func:`minus_log` takes the clamped
``-log``. ``bubsub prepare`` builds its model from a raw file's flats
(:func:`bubsub.core.prep.flats.flat_model`); a scan file that holds raw
counts is corrected with :func:`mean_flat_model` of its flat and dark when
it is read (:func:`bubsub.core.io.scanfile.read_scan`). The correction sits
here, below both, so that each uses the same one.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["FlatModel", "mean_flat_model", "minus_log"]


@dataclasses.dataclass(frozen=True, eq=False)
class FlatModel:
    """Averaged flats and darks of a ROI, and the bad-pixel map.

    Attributes
    ----------
    mode : {"mean", "interp", "best", "none"}
    dark : (rows, cols) float32
    flats : (g, rows, cols) float32
        Group means (``interp``: before, after; ``mean``: one).
    times : (g,) float
        Projection-index time of each group (``interp``).
    bad : (rows, cols) bool
    air : (rows, cols) bool or None
        Open-beam pixels used by ``best``.
    """

    mode: str
    dark: np.ndarray
    flats: np.ndarray
    times: np.ndarray
    bad: np.ndarray
    air: np.ndarray | None = None

    def __repr__(self):
        return (f"FlatModel(mode={self.mode!r}, groups={self.flats.shape[0]}, shape={self.dark.shape}, "
                f"bad_pixels={int(self.bad.sum())})")

    def crop(self, rows, cols):
        """The model of a sub-region (``rows``, ``cols``: slices of this model's ROI)."""
        air = None if self.air is None else self.air[rows, cols]
        return FlatModel(self.mode, self.dark[rows, cols], self.flats[:, rows, cols], self.times,
                         self.bad[rows, cols], air)

    def transmission(self, counts, index):
        """Intensity transmission of a slab of raw counts.

        Parameters
        ----------
        counts : (k, rows, cols) float32
        index : (k,) int
            Raw projection indices (times for ``interp``).

        Returns
        -------
        (k, rows, cols) float32, and a list of the flat group used per
        projection (``best``) or None.
        """
        c = counts - self.dark
        with np.errstate(divide="ignore", invalid="ignore"):
            t, chosen = self._divide(c, index)
        # dead pixels divide by zero: give them a neutral value until they are repaired
        t[~np.isfinite(t)] = 1.0
        return t.astype(np.float32, copy=False), chosen

    def _divide(self, c, index):
        if self.mode == "none":
            # No flats: normalise each projection by its brightest (open-beam) level.
            level = np.percentile(c.reshape(len(c), -1), 99.5, axis=1)
            return (c / np.maximum(level, 1e-6)[:, None, None]).astype(np.float32), None
        span = self.flats - self.dark
        if self.mode == "mean":
            return c / span[0], None
        if self.mode == "interp":
            t0, t1 = self.times
            w = np.clip((np.asarray(index, dtype=float) - t0) / (t1 - t0), 0.0, 1.0)[:, None, None]
            return c / ((1 - w) * span[0] + w * span[-1]), None
        chosen = []
        out = np.empty_like(c)
        air = self.air
        for i, img in enumerate(c):
            ratios = img[air][None, :] / span[:, air]
            scale = np.median(ratios, axis=1)
            score = np.std(ratios / scale[:, None], axis=1)
            g = int(np.argmin(score))
            chosen.append(g)
            out[i] = img / (span[g] * scale[g])
        return out, chosen


def mean_flat_model(flat, dark):
    """The ``mean`` model of one averaged flat and dark (any detector shape), with no bad pixels.

    What a scan file holding raw counts (``/exchange/data_white``) is corrected with when read.
    """
    flat = np.asarray(flat)
    return FlatModel("mean", np.asarray(dark), flat[None], np.zeros(1), np.zeros(flat.shape, bool))


def minus_log(transmission, min_transmission):
    """Line integrals ``-log(max(t, min_transmission))``; ``transmission`` is clamped in place.

    Parameters
    ----------
    transmission : float array
    min_transmission : float
        Lowest transmission kept (in (0, 1)): opaque or noisy pixels would give ``inf`` or huge values.

    Returns
    -------
    float array of the same shape and dtype
    """
    np.maximum(transmission, min_transmission, out=transmission)
    return -np.log(transmission)
