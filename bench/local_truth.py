"""The truths of ``python -m bubsub.bench fov``'s local-tomography cases (:mod:`bubsub.bench.fov_local`) that
``bubsub prepare`` estimates: the true bubbles on a grid, the liquid's exact projection and the true bubbles' mean
projection over the angles beyond the reach of the reconstruction's model."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bubsub.core.io.meshio import read_polygons_json
from bubsub.core.prep import background as bgmod
from bubsub.core.projection.masks import label_image

__all__ = ["truth_gas", "true_background", "mean_projection_beyond"]


def truth_gas(out, s, pixels=1200):
    """The true bubbles of the raw simulation under ``out`` (settings ``s``) on a square grid over the liquid's
    disc: ``(gas, r)``, the bubbles' pixels and every pixel's distance from the axis (mm)."""
    r_true = s.container_radius
    gas = label_image(read_polygons_json(Path(out) / "truth.json"), (pixels, pixels), (-r_true, r_true) * 2) > 0
    yy, xx = (np.mgrid[:pixels, :pixels] + 0.5) * (2 * r_true / pixels) - r_true
    return gas, np.hypot(xx, yy)


def true_background(out, s, offsets, truth=None, reach=None):
    """What ``bubsub prepare --background auto`` estimates for the raw simulation under ``out`` at the detector
    ``offsets`` (mm from the axis): the liquid's exact projection, and the true bubbles' mean projection over the
    angles beyond :data:`~bubsub.core.prep.background.FOAM_BEYOND_REACH` field-of-view radii (gas: the liquid's
    attenuation less; ``reach`` field-of-view radii instead where given, ``inf``: none). ``(liquid, beyond)``,
    each ``(cols,)``; ``truth``: :func:`truth_gas`'s, if made."""
    liquid = s.liquid_mu * 2 * np.sqrt(s.container_radius ** 2 - offsets ** 2)
    r_from = (bgmod.FOAM_BEYOND_REACH if reach is None else reach) * float(min(-offsets[0], offsets[-1]))
    if r_from >= s.container_radius:
        return liquid, np.zeros_like(liquid)
    gas, r = truth_gas(out, s) if truth is None else truth
    return liquid, mean_projection_beyond(gas, r, r_from, s.container_radius, -s.liquid_mu, offsets)


def mean_projection_beyond(gas, r, r_from, r_to, contrast, offsets):
    """The mean over the angles of the projection of ``contrast`` times the ``gas`` raster (:func:`truth_gas`'s
    square grid over the disc of radius ``r_to``, ``r`` its pixels' distances from the axis) between ``r_from`` and
    ``r_to`` (mm), at the detector ``offsets``: the Abel transform of the raster's ring means, rings a pixel wide."""
    step = 2 * r_to / gas.shape[-1]
    edges = np.arange(r_from, r_to + step, step)
    ring = np.digitize(r, edges) - 1
    inside = (ring >= 0) & (ring < len(edges) - 1)
    counts = np.bincount(ring[inside], minlength=len(edges) - 1)
    means = np.bincount(ring[inside], weights=gas[inside], minlength=len(edges) - 1) / np.maximum(counts, 1)
    centres = 0.5 * (edges[:-1] + edges[1:])
    t = np.arange(0.5 * step, r_to, 0.5 * step)
    rho = np.hypot(np.asarray(offsets)[:, None], t[None])
    profile = np.where((rho >= r_from) & (rho <= r_to), np.interp(rho, centres, means), 0.0)
    return 2 * contrast * profile.sum(axis=1) * 0.5 * step
