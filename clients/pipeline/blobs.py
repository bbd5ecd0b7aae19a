"""Multi-scale blob detection on a voxel image of the bubbles (Laplacian of Gaussian).

At few views the voxel preview blurs neighbouring bubbles into one region of
its Otsu mask, and small bubbles fall below the threshold or the morphological
opening; the distance-transform maxima of that mask then miss and merge
bubbles. A scale-normalised Laplacian of Gaussian (scikit-image's
``blob_log``) responds to each roughly round bright region at its own scale,
touching or not, and gives a radius with it (``sqrt(ndim) * sigma``).

Used for the initial bubbles (:func:`bubsub.clients.pipeline.initial.initial_surfaces`
with ``detector="log"``) and, on a back-projected residual, for bubbles added
during the fit (:mod:`bubsub.clients.pipeline.topology`).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from bubsub.core.voxel.grid import index_to_world

__all__ = ["log_blobs"]


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
    from skimage.feature import blob_log

    img = np.asarray(image, dtype=float) / abs(float(contrast))
    ndim = img.ndim
    voxel = (extent[1] - extent[0]) / img.shape[-1]
    if not 0 < min_radius < max_radius:
        raise ValueError(f"need 0 < min_radius < max_radius, got {min_radius!r}, {max_radius!r}")
    k = np.sqrt(ndim)
    # skimage's own pruning keeps the larger of two overlapping blobs, which makes a
    # cluster of bubbles one big blob; keep the strongest response instead (below)
    blobs = blob_log(img, min_sigma=min_radius / voxel / k, max_sigma=max_radius / voxel / k,
                     num_sigma=int(num_sigma), threshold=float(threshold), overlap=1.0, exclude_border=False)
    if len(blobs) == 0:
        return np.zeros((0, ndim)), np.zeros(0)
    idx = np.clip(np.round(blobs[:, :ndim]).astype(int), 0, np.array(img.shape) - 1)
    if mask is not None:
        inside = np.asarray(mask)[tuple(idx.T)]
        blobs, idx = blobs[inside], idx[inside]
    strength = np.zeros(len(blobs))
    for sigma in np.unique(blobs[:, ndim]):
        at = blobs[:, ndim] == sigma
        response = -sigma**2 * ndimage.gaussian_laplace(img, sigma)  # scale-normalised, bright blobs positive
        strength[at] = response[tuple(idx[at].T)]
    order = np.argsort(-strength, kind="stable")
    keep = []
    for i in order:  # non-maximum suppression: two blobs overlap by less than half the smaller one's radius
        r_i = blobs[i, ndim] * k
        if all(np.linalg.norm(blobs[i, :ndim] - blobs[j, :ndim])
               > max(r_i, blobs[j, ndim] * k) + 0.5 * min(r_i, blobs[j, ndim] * k) for j in keep):
            keep.append(i)
    blobs = blobs[keep]
    return index_to_world(blobs[:, :ndim], img.shape, extent), blobs[:, ndim] * k * voxel
