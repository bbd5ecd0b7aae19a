"""Multi-scale blob detection on a voxel image of the bubbles (Laplacian of Gaussian).

At few views the voxel preview blurs neighbouring bubbles into one region of
its Otsu mask, and small bubbles fall below the threshold or the morphological
opening; the distance-transform maxima of that mask then miss and merge
bubbles. A scale-normalised Laplacian of Gaussian (scikit-image's
``blob_log``) responds to each roughly round bright region at its own scale,
touching or not, and gives a radius with it (``sqrt(ndim) * sigma``).

Used for the initial bubbles (:func:`bubsub.clients.pipeline.static.initial.initial_surfaces`
with ``detector="log"``), for the small bubbles that the distance-transform
detector's morphological opening erases (:func:`small_blobs`) and, on a
back-projected residual, for bubbles added during the fit
(:mod:`bubsub.clients.pipeline.static.topology`).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage.feature import peak_local_max

from bubsub.core.projection.projector import default_threads
from bubsub.core.threads import thread_map
from bubsub.core.voxel.grid import index_to_world, voxel_sizes, world_to_index
from bubsub.core.voxel.segment import otsu_threshold

__all__ = ["log_blobs", "small_blobs", "SMALL_BLOB_VOXELS"]


def log_blobs(image, extent, contrast, *, min_radius, max_radius, threshold=0.1, mask=None, num_sigma=12):
    """Bright blobs of a bubble image: centres (mm) and radii (mm), largest response first.

    Parameters
    ----------
    image : (rows, cols) or (slices, rows, cols) float
        Bubble "density": about ``|contrast|`` inside bubbles, 0 outside.
    extent : (xmin, xmax, ymin, ymax[, zmin, zmax])
        mm (grid convention of :mod:`bubsub.core.voxel.grid`).
    contrast : float
        Bubble attenuation, 1/mm; the image is divided by ``|contrast|`` so
        that ``threshold`` is a fraction of a full bubble's response.
    min_radius, max_radius : float
        Range of bubble radii searched, mm.
    threshold : float
        Least scale-normalised LoG response, as a fraction of ``|contrast|``.
    mask : bool array of the image's shape, optional
        Keep only blobs whose centre voxel is in the mask (e.g. the Otsu mask,
        to reject streaks outside the gas).
    num_sigma : int
        Scales tried between the two radii.

    Returns
    -------
    centres : (k, ndim) float
        ``[x, y]`` or ``[x, y, z]``, mm.
    radii : (k,) float
        mm. Of two blobs whose discs (balls) overlap by more than half the
        smaller radius, only the stronger scale-normalised response is kept.
    """
    img = np.asarray(image, dtype=float) / abs(float(contrast))
    ndim = img.ndim
    voxel = (extent[1] - extent[0]) / img.shape[-1]
    if not 0 < min_radius < max_radius:
        raise ValueError(f"need 0 < min_radius < max_radius, got {min_radius!r}, {max_radius!r}")
    k = np.sqrt(ndim)
    # skimage's own pruning keeps the larger of two overlapping blobs, which makes a
    # cluster of bubbles one big blob; keep the strongest response instead (below)
    peaks, sigmas, strength = _blob_log(img, min_radius / voxel / k, max_radius / voxel / k, int(num_sigma),
                                        float(threshold))
    if len(peaks) == 0:
        return np.zeros((0, ndim)), np.zeros(0)
    if mask is not None:
        inside = np.asarray(mask)[tuple(peaks[:, :ndim].T)]
        peaks, strength = peaks[inside], strength[inside]  # the scale-normalised response, bright blobs positive
    blobs = np.c_[peaks[:, :ndim].astype(float), sigmas[peaks[:, ndim]]]
    order = np.argsort(-strength, kind="stable")
    keep = []
    for i in order:  # non-maximum suppression: two blobs overlap by less than half the smaller one's radius
        r_i = blobs[i, ndim] * k
        if all(np.linalg.norm(blobs[i, :ndim] - blobs[j, :ndim])
               > max(r_i, blobs[j, ndim] * k) + 0.5 * min(r_i, blobs[j, ndim] * k) for j in keep):
            keep.append(i)
    blobs = blobs[keep]
    return index_to_world(blobs[:, :ndim], img.shape, extent), blobs[:, ndim] * k * voxel


#: Radii (in voxels of the image) that :func:`small_blobs` searches: a bubble narrower than the opening's ball
#: of 2 voxels' radius (:func:`bubsub.clients.pipeline.static.initial.initial_centres`) is gone from the opened mask.
SMALL_BLOB_VOXELS = (1.5, 4.0)


def small_blobs(image, extent, contrast, *, kept, threshold=0.3, voxels=SMALL_BLOB_VOXELS):
    """Bubbles a few voxels across that a bubble mask lost: bright blobs of the image outside ``kept``.

    A distance-transform detector opens its Otsu mask with a ball of 2 voxels'
    radius to drop noise; a bubble not much wider than that ball goes with
    it, although the image shows it well above the threshold (flowing-foam
    and small-bubble columns of ``bubsub bench detection``: bubbles of 4-6
    pixels' radius at 2.4 pixels a voxel peak at 0.55-1.0 of the contrast,
    the Otsu threshold at 0.46). Each such bubble is a scale-normalised
    LoG blob (:func:`log_blobs`) of ``voxels`` radius whose centre voxel is
    above the image's Otsu threshold and whose ball stays clear of ``kept``.

    Parameters
    ----------
    image : (rows, cols) or (slices, rows, cols) float
        Bubble "density": about ``|contrast|`` inside bubbles, 0 outside.
    extent : tuple
        mm (grid convention of :mod:`bubsub.core.voxel.grid`).
    contrast : float
        Bubble attenuation, 1/mm.
    kept : bool array of the image's shape
        The bubbles already accounted for (the opened mask whose distance
        maxima seed them).
    threshold : float
        Least scale-normalised LoG response, as a fraction of ``|contrast|``.
    voxels : (float, float)
        Range of radii searched, voxels.

    Returns
    -------
    centres : (k, ndim) float
        mm, strongest response first.
    radii : (k,) float
        mm.
    """
    img = np.asarray(image, dtype=float)
    kept = np.asarray(kept, dtype=bool)
    if kept.shape != img.shape:
        raise ValueError(f"kept must have the image's shape {img.shape}, got {kept.shape}")
    voxel = (extent[1] - extent[0]) / img.shape[-1]
    # the mask applies before the overlap pruning: a bubble kept beside a lost one does not suppress it
    centres, radii = log_blobs(img, extent, contrast, min_radius=voxels[0] * voxel, max_radius=voxels[1] * voxel,
                               threshold=threshold, mask=~kept & (img > otsu_threshold(img)))
    if len(centres) == 0 or not kept.any():
        return centres, radii
    # a blob whose ball reaches into ``kept`` is the rim of a kept bubble that the opening trimmed (at a grid
    # edge taken as background: 0.5-0.7 of its radius away), not a bubble of its own (2.5 radii and more on
    # the small-bubble column of bench detection)
    idx = np.clip(np.round(world_to_index(centres, img.shape, extent)).astype(int), 0, np.array(img.shape) - 1)
    away = ndimage.distance_transform_edt(~kept, sampling=voxel_sizes(img.shape, extent))[tuple(idx.T)]
    clear = away >= radii
    return centres[clear], radii[clear]


def _blob_log(img, min_sigma, max_sigma, num_sigma, threshold):
    """scikit-image's ``blob_log(img, min_sigma, max_sigma, num_sigma, threshold, overlap=1.0,
    exclude_border=False)``, with its scale space computed a few scales at a time, one scale per thread.

    The same scales, scale normalisation and local maxima as scikit-image 0.26's ``blob_log`` and its
    ``peak_local_max`` call (overlap 1 prunes nothing; ``tests/test_topology.py`` checks the result against
    ``blob_log``), written out because ``blob_log`` computes its 12 Laplacians one after the other (1.1 s of a
    3D reconstruction, serial) and holds the whole scale space, with a maximum filter of it as large: on a
    3D preview of 54 x 160 x 160 voxels the two took 290 MB at once, the peak memory of a warm subscan of
    ``reconstruct4d``. The maximum over a box of 3 voxels by 3 scales is separable: each scale's maximum
    over its voxels, then over the scale and its two neighbours (an end scale counted twice, scipy's
    ``mode="nearest"``), so only the scales around the one searched are held.

    Returns
    -------
    peaks : (k, ndim + 1) int
        Voxel index and scale index of each local maximum above ``threshold``, highest response first
        (``peak_local_max``'s order).
    sigmas : (num_sigma,) float
        The scales, voxels.
    strength : (k,) float
        The scale-normalised response ``-sigma^2 LoG_sigma(img)`` at each peak.
    """
    ndim = img.ndim
    scales = np.linspace(np.full(ndim, min_sigma), np.full(ndim, max_sigma), num_sigma)  # (num_sigma, ndim)
    threads = max(1, min(default_threads(), num_sigma))

    def one(i):  # scipy.ndimage releases the GIL: the scales run in parallel
        response = -ndimage.gaussian_laplace(img, scales[i]) * np.mean(scales[i]) ** 2
        return response, ndimage.maximum_filter(response, size=3, mode="nearest")

    held, found, values = {}, [], []
    trivial = True  # peak_local_max finds nothing in an image equal to its maximum filter everywhere
    for i in range(num_sigma):
        ahead = [j for j in range(i, min(num_sigma, i + 2)) if j not in held]
        if ahead:
            batch = list(range(ahead[0], min(num_sigma, ahead[0] + max(threads, len(ahead)))))
            held.update(zip(batch, thread_map(one, batch, threads)))
        response, top = held[i][0], np.maximum(held[max(i - 1, 0)][1], held[i][1])
        np.maximum(top, held[min(i + 1, num_sigma - 1)][1], out=top)
        peak = response == top
        trivial = trivial and bool(peak.all())
        peak &= response > threshold
        index = np.nonzero(peak)
        found.append(np.column_stack(index + (np.full(len(index[0]), i),)).astype(np.intp))
        values.append(response[index])
        held.pop(i - 1, None)
    if trivial:
        return np.zeros((0, ndim + 1), np.intp), scales[:, 0], np.zeros(0)
    peaks, strength = np.concatenate(found), np.concatenate(values)
    order = np.lexsort(peaks.T[::-1])  # the scale space's C order: voxel index, then scale
    peaks, strength = peaks[order], strength[order]
    order = np.argsort(-strength, kind="stable")  # highest first, as peak_local_max
    return peaks[order], scales[:, 0], strength[order]
