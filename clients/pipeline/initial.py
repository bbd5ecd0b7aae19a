"""Initial bubbles: centres and radii found in the voxel preview, one round bubble each.

Two detectors, each right where the other fails (docs/robustness.md):

* ``"log"``: scale-normalised Laplacian-of-Gaussian blobs
  (:func:`bubsub.clients.pipeline.blobs.log_blobs`). At few views the preview
  blurs neighbouring round bubbles together; LoG still responds to each at its
  own scale (fig1a, 10 views: 35 of 40 bubbles found with no spurious ones,
  against 31 and 5 spurious).
* ``"dt"``: maxima of the distance transform of the preview's Otsu mask.
  Right for dense foams, whose polygonal cells LoG splits or misses (dense 2D
  foam, 25 views: 12 of 12 against 5 of 12).

``"auto"`` (:func:`choose_initial`, the 2D default) builds both sets, sizes
each by the radius-only fit and keeps the one with the lower Akaike score
of the projection distance. In 3D the default is ``"dt"``: at the 2D
threshold LoG finds 167 centres for the 12 bubbles of the dense 3D foam.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from bubsub.core import circle_surface, sphere_surface

__all__ = ["LOG_THRESHOLD", "initial_centres", "initial_surfaces", "choose_initial", "default_detector"]


def default_detector(detector, ndim):
    """``detector``, or the default for ``ndim`` when it is None: ``"auto"`` in 2D, ``"dt"`` in 3D."""
    return ("auto" if ndim == 2 else "dt") if detector is None else detector


#: least scale-normalised LoG response of an initial bubble, as a fraction of ``|contrast|``
#: (fig1a, 10 views, seeds 0-1: 0.25 puts two centres in 3 elongated bubbles, 0.35 misses 7-9; docs/robustness.md)
LOG_THRESHOLD = 0.3


def initial_centres(image, extent, *, detector="dt", min_distance=None, contrast=1.0, border_is_background=True):
    """Bubble centres and radii (mm) in a voxel preview.

    ``"log"``: scale-normalised Laplacian-of-Gaussian blobs
    (:func:`bubsub.clients.pipeline.blobs.log_blobs`, radii 2 voxels to 1/8
    of the field of view), which responds to each round bright region at its
    own scale, touching or not. ``"dt"``: local maxima of the distance
    transform of the preview's Otsu mask, which merges bubbles whose blurred
    images touch (at 10 views, 31 of 40 bubbles found instead of 35;
    docs/robustness.md). ``min_distance`` (mm) applies to ``"dt"`` only, and
    so does ``border_is_background``: False when the grid's edge is the edge
    of what the data see (the field-of-view model), so that a bubble cut by
    it keeps its centre and the radius of its visible cross-section.

    Returns
    -------
    centres : (k, ndim) float
        mm.
    radii : (k,) float
        mm.
    """
    from bubsub.core.voxel.segment import binarise, bubble_centres, mask_distance

    voxel = (extent[1] - extent[0]) / image.shape[-1]
    if detector == "log":
        from bubsub.clients.pipeline.blobs import log_blobs

        return log_blobs(image, extent, contrast, min_radius=2 * voxel, max_radius=(extent[1] - extent[0]) / 8,
                         threshold=LOG_THRESHOLD)
    if detector != "dt":
        raise ValueError(f"detector must be 'log' or 'dt', got {detector!r}")
    # where the grid's edge is the edge of the data, the opening must not eat the bubbles it cuts: extend
    # the image beyond its edge by its edge values first
    pad = 0 if border_is_background else 3
    mask = binarise(np.pad(image, pad, mode="edge"), opening_radius=2, bubbles_are_dark=False, fill_holes=True)
    mask = mask[tuple(slice(pad, n - pad) for n in mask.shape)]
    # maxima thinner than two voxels are noise that survived the opening
    kw = dict(min_radius=2 * voxel, border_is_background=border_is_background,
              distance=mask_distance(mask, extent, border_is_background=border_is_background))
    centres, radii = bubble_centres(mask, extent, min_distance=min_distance, **kw)
    if min_distance is None and len(radii):
        # one centre per bubble: maxima closer than the typical bubble radius belong together
        centres, radii = bubble_centres(mask, extent, min_distance=max(3 * voxel, float(np.median(radii))), **kw)
    return centres, radii


def initial_surfaces(image, extent, contrast, *, control_points=None, levels=2, radius=None, min_distance=None,
                     detector="dt", border_is_background=True):
    """Spherical bubbles at the centres :func:`initial_centres` finds in the preview.

    Parameters
    ----------
    image : ndarray
        :func:`voxel_preview` (bubbles positive).
    extent : tuple
    contrast : float
        Bubble attenuation (gas minus liquid), 1/mm.
    control_points : int, optional
        42 (3D) / 9 (2D) by default.
    radius : float, optional
        Constant initial radius, mm; default each blob's radius (``"log"``)
        or the median of the distance transform at the centres (``"dt"``).
        Each bubble's radius is capped at half the distance to its nearest
        neighbour, so initial bubbles never overlap.
    detector : {"dt", "log"}
    border_is_background : bool
        See :func:`initial_centres`.

    Returns
    -------
    list of SubdivisionSurface
    """
    ndim = image.ndim
    centres, radii = initial_centres(image, extent, detector=detector, min_distance=min_distance, contrast=contrast,
                                     border_is_background=border_is_background)
    if len(centres) == 0:
        raise ValueError("no bubbles found in the voxel reconstruction; give an initial mesh with --init")
    if radius is not None:
        r = np.full(len(centres), float(radius))
    elif detector == "log":  # each blob's own radius
        r = np.asarray(radii, dtype=float)
    else:
        r = np.full(len(centres), float(np.median(radii)))
    if not np.all(r > 0):
        raise ValueError(f"initial radius must be positive, got {radius if radius is not None else r.min()}")
    # Overlapping initial bubbles count their overlap twice and can lock each other
    # in a poor local minimum: cap each radius at half the distance to the nearest centre.
    if len(centres) > 1:
        nearest, _ = cKDTree(centres).query(centres, k=2)
        r = np.minimum(r, 0.5 * nearest[:, 1])
    if ndim == 3:
        k = control_points or 42
        return [sphere_surface(c, rk, contrast, control=k, levels=levels) for c, rk in zip(centres, r)]
    k = control_points or 9
    return [circle_surface(c, rk, contrast, control=k, levels=levels) for c, rk in zip(centres, r)]


_NAMES = {"log": "LoG", "dt": "distance-transform"}  # phase labels of the candidate sets


def choose_initial(image, extent, contrast, projector, data, *, detector="auto", estimate=True, progress=False,
                   **options):
    """Initial bubbles from the detector that explains the data best.

    Parameters
    ----------
    image, extent, contrast
        As :func:`initial_surfaces`.
    projector : MeshProjector
        Of ``data`` (a local one: both candidate sets are projected).
    data : ndarray
        The fitted projections.
    detector : {"auto", "log", "dt"}
        ``"auto"``: both sets are made, sized by the radius-only fit
        (:func:`bubsub.clients.optimise.fit.estimate_radii`) when ``estimate``,
        and scored by ``m log(2 f / m) + 2 k``: the Akaike criterion of the
        projection distance ``f`` over the ``m`` data values with ``k``
        unknowns (control coordinates), so that extra bubbles must earn their
        place. Else only that detector.
    options
        ``control_points``, ``levels``, ``radius``, ``min_distance``,
        ``border_is_background`` of :func:`initial_surfaces`.

    Returns
    -------
    surfaces : list of SubdivisionSurface
        Radius-fitted when ``estimate``.
    summary : dict
        ``detector`` (the one used) and, per candidate, ``bubbles``,
        ``objective`` and ``score`` (``"auto"`` only), or ``None`` (no error)
        for a candidate that found no bubbles.
    """
    from bubsub.clients.optimise.criteria import akaike_score
    from bubsub.clients.optimise.fit import estimate_radii

    if detector not in ("auto", "log", "dt"):
        raise ValueError(f"detector must be 'auto', 'log' or 'dt', got {detector!r}")
    names = ("log", "dt") if detector == "auto" else (detector,)
    data = np.asarray(data)
    candidates, summary = {}, {}
    for name in names:
        try:
            surfaces = initial_surfaces(image, extent, contrast, detector=name, **options)
        except ValueError:
            if len(names) == 1:
                raise
            summary[name] = None
            continue
        if estimate:
            label = f"radius estimation ({_NAMES[name]} centres)" if len(names) > 1 else "radius estimation"
            surfaces = estimate_radii(projector, surfaces, data, progress=progress, label=label)
        candidates[name] = surfaces
        if len(names) > 1:
            f = float(projector.objective(surfaces, data)[0])
            summary[name] = {"bubbles": len(surfaces), "objective": f,
                             "score": akaike_score(f, data.size, sum(s.vertices.size for s in surfaces))}
    if not candidates:
        raise ValueError("no bubbles found in the voxel reconstruction; give an initial mesh with --init")
    best = min(candidates, key=lambda n: summary[n]["score"]) if len(names) > 1 else names[0]
    summary["detector"] = best
    return candidates[best], summary
