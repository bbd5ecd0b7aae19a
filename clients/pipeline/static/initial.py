"""Initial bubbles: centres and radii found in the voxel preview, one round bubble each.

Two detectors, each right where the other fails (docs/robustness.md):

* ``"log"``: scale-normalised Laplacian-of-Gaussian blobs
  (:func:`bubsub.clients.pipeline.static.blobs.log_blobs`). At few views the preview
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
from bubsub.clients.optimise.criteria import akaike_score
from bubsub.clients.optimise.fit import estimate_radii
from bubsub.clients.pipeline.static.blobs import log_blobs, small_blobs
from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.voxel.astra2d import reconstruct_2d
from bubsub.core.voxel.segment import binarise, bubble_centres, mask_distance

__all__ = ["LOG_THRESHOLD", "initial_centres", "distance_centres", "small_centres", "initial_surfaces", "choose_initial", "default_detector", "edge_slices",
           "edge_centres", "row_pixel", "EDGE_ITERATIONS", "HALF_HEIGHT_OVER_RADIUS", "MIN_DISC_PIXELS"]


def default_detector(detector, ndim):
    """``detector``, or the default for ``ndim`` when it is None: ``"auto"`` in 2D, ``"dt"`` in 3D."""
    return ("auto" if ndim == 2 else "dt") if detector is None else detector


#: least scale-normalised LoG response of an initial bubble, as a fraction of ``|contrast|``
#: (fig1a, 10 views, seeds 0-1: 0.25 puts two centres in 3 elongated bubbles, 0.35 misses 7-9; docs/robustness.md)
LOG_THRESHOLD = 0.3


def initial_centres(image, extent, *, detector="dt", min_distance=None, contrast=1.0, border_is_background=True):
    """Bubble centres and radii (mm) in a voxel preview.

    ``"log"``: scale-normalised Laplacian-of-Gaussian blobs
    (:func:`bubsub.clients.pipeline.static.blobs.log_blobs`, radii 2 voxels to 1/8
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
    voxel = (extent[1] - extent[0]) / image.shape[-1]
    if detector == "log":
        return log_blobs(image, extent, contrast, min_radius=2 * voxel, max_radius=(extent[1] - extent[0]) / 8,
                         threshold=LOG_THRESHOLD)
    if detector != "dt":
        raise ValueError(f"detector must be 'log' or 'dt', got {detector!r}")
    return distance_centres(image, extent, min_distance=min_distance, border_is_background=border_is_background)[:2]


def distance_centres(image, extent, *, min_distance=None, border_is_background=True):
    """The ``"dt"`` detector of :func:`initial_centres`, with the mask it searched.

    The preview's Otsu mask, opened with a ball of 2 voxels' radius (noise
    out) and its holes filled; the local maxima of its distance transform at
    least 2 voxels deep, one per ``min_distance`` (default: the median
    maximum's radius, at least 3 voxels).

    Returns
    -------
    centres : (k, ndim) float
        mm.
    radii : (k,) float
        The distance transform at each centre, mm.
    mask : bool ndarray of the image's shape
        The opened mask (:func:`small_centres` looks outside it).
    """
    voxel = (extent[1] - extent[0]) / image.shape[-1]
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
    return centres, radii, mask


def small_centres(image, extent, contrast, mask):
    """Bubbles a few voxels across that the ``"dt"`` detector's opening erased, as centres and radii (mm).

    :func:`bubsub.clients.pipeline.static.blobs.small_blobs` outside ``mask``
    (:func:`distance_centres`' opened mask), at :data:`LOG_THRESHOLD`. On the
    small-bubble column of ``bubsub bench detection`` (``--seed 1
    --small-share 0.5 --small-range 4 9``, preview voxels of 2.4 pixels) the
    distance maxima seed 29 of its 33 bubbles of 6-12 pixels' radius and 2
    of its 30 under 6 pixels; these blobs add 28 centres, each inside a
    bubble none seeded (4, 1 cap and 23 under 6 pixels), none in the liquid
    (23 once those crossing the edge slices are left out, below).
    In 3D a blob whose ball crosses the grid's first or last slice is left
    out: the caps that the detector's top and bottom rows cut are seeded
    from those rows (:func:`edge_slices`), beyond the edge plane.
    """
    centres, radii = small_blobs(image, extent, contrast, kept=mask, threshold=LOG_THRESHOLD)
    if image.ndim == 3 and len(centres):
        inside = (centres[:, 2] - radii >= extent[4]) & (centres[:, 2] + radii <= extent[5])
        centres, radii = centres[inside], radii[inside]
    return centres, radii


def initial_surfaces(image, extent, contrast, *, control_points=None, levels=2, radius=None, min_distance=None,
                     detector="dt", border_is_background=True, edges=None):
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
        With ``"dt"`` in 3D, the bubbles its opening erased (:func:`small_centres`)
        are added, each at its blob's radius (at most the common one).
    border_is_background : bool
        See :func:`initial_centres`.
    edges : list of (plane, outward, centres, radii), optional
        :func:`edge_slices`: the discs that bubbles cut by the detector's top
        and bottom edge show on the edge rows. Each disc no bubble found in
        the preview accounts for becomes one more bubble, placed so that its
        sphere (the common initial radius) has that disc as its cross-section
        with the edge plane (:func:`edge_centres`): a thin visible cap, which
        the preview's voxels do not resolve, is seeded as such a cap.

    Returns
    -------
    list of SubdivisionSurface
    """
    ndim = image.ndim
    small = np.zeros((0, ndim)), np.zeros(0)
    if detector == "dt" and ndim == 3:
        centres, radii, mask = distance_centres(image, extent, min_distance=min_distance,
                                                border_is_background=border_is_background)
        small = small_centres(image, extent, contrast, mask)
    else:
        centres, radii = initial_centres(image, extent, detector=detector, min_distance=min_distance,
                                         contrast=contrast, border_is_background=border_is_background)
    if len(centres) + len(small[0]) == 0:
        raise ValueError("no bubbles found in the voxel reconstruction; give an initial mesh with --init")
    if radius is not None:
        r = np.full(len(centres), float(radius))
    elif detector == "log":  # each blob's own radius
        r = np.asarray(radii, dtype=float)
    else:
        r = np.full(len(centres), float(np.median(radii if len(radii) else small[1])))
    if len(small[0]):  # the small bubbles the opening erased: each its blob's radius, never above the others'
        centres = np.concatenate([centres, small[0]])
        r = np.concatenate([r, np.minimum(small[1], float(np.median(r)) if len(r) else np.inf)])
    if not np.all(r > 0):
        raise ValueError(f"initial radius must be positive, got {radius if radius is not None else r.min()}")
    if edges and ndim == 3:
        extra = edge_centres(centres, r, edges, float(np.median(r)))
        if len(extra):
            centres = np.concatenate([centres, extra])
            r = np.concatenate([r, np.full(len(extra), float(np.median(r)))])
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
        ``border_is_background`` of :func:`initial_surfaces`; with
        ``border_is_background=False`` (the field-of-view model) in 3D, the
        discs of :func:`edge_slices` at half the preview's voxel size are added
        as ``edges``.

    Returns
    -------
    surfaces : list of SubdivisionSurface
        Radius-fitted when ``estimate``.
    summary : dict
        ``detector`` (the one used) and, per candidate, ``bubbles``,
        ``objective`` and ``score`` (``"auto"`` only), or ``None`` (no error)
        for a candidate that found no bubbles.
    """
    if detector not in ("auto", "log", "dt"):
        raise ValueError(f"detector must be 'auto', 'log' or 'dt', got {detector!r}")
    names = ("log", "dt") if detector == "auto" else (detector,)
    data = np.asarray(data)
    if not options.get("border_is_background", True) and image.ndim == 3:
        # the field-of-view model: bubbles cut by the detector's top and bottom, seen on the edge rows
        voxel = (extent[1] - extent[0]) / image.shape[-1]
        options = dict(options, edges=edge_slices(data, projector.geometry, contrast, extent, voxel / 2))
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


#: Box-constrained BB iterations of each edge row's slice (:func:`edge_slices`).
EDGE_ITERATIONS = 30

#: Least radius of an edge disc (:func:`edge_slices`), in the slice's pixels.
MIN_DISC_PIXELS = 3


def row_pixel(geometry):
    """A detector row's height on the detector, mm (in a parallel-beam scan, a slice's thickness)."""
    return float(np.linalg.norm(geometry.vectors[0, 9:12]))


def edge_slices(data, geometry, contrast, extent, voxel):
    """Discs of bubble cut by the detector's top and bottom edge, found on the edge rows' slices.

    In a parallel-beam scan whose rows are slices of the sample, the first and
    last detector rows see the two slices at the edge of the field of view.
    Each is reconstructed alone as a 2D scan (box-constrained BB,
    :data:`EDGE_ITERATIONS` iterations, pixels of ``voxel``) and its distance-transform
    maxima are the discs that the bubbles crossing the edge cut from it, however
    thin their visible cap: the low-resolution preview, whose voxels are several
    rows thick, averages a cap thinner than about two of them away.

    Parameters
    ----------
    data : ndarray, ``(views, rows, cols)``
        The fitted projections' bubble signal.
    geometry : ScanGeometry
        Of ``data``.
    contrast : float
    extent : tuple
        Of the voxel preview, mm: the slices span its ``x`` and ``y`` range.
    voxel : float
        Pixel of the slices, mm (at least one detector column; two columns binned
        where it is at least two).

    Returns
    -------
    list of (plane, outward, centres, radii)
        One per edge: its height (mm), +1 (top) or -1 (bottom), the discs' centres
        ``(k, 2)`` and radii ``(k,)`` (mm). Empty for a cone-beam or 2D scan (rows
        are not slices there) and for fewer than 8 rows.
    """
    g = geometry
    if g.ndim != 3 or g.is_cone or g.det_rows < 8:
        return []
    vec = g.vectors
    if np.abs(vec[:, [2, 8]]).max() > 1e-9 * np.abs(vec[:, 6:9]).max():
        return []  # rays or detector columns tilted out of the horizontal plane: a row is no slice
    # each row's 2D scan: the rays, the row's centre and the column direction in the horizontal plane; pairs of
    # columns binned where the slice's pixels are at least two columns wide (half the projector's work), and
    # pixels no finer than the columns (finer ones only resolve noise)
    pixel = float(np.linalg.norm(vec[0, 6:9]))
    binning = 2 if voxel >= 2 * pixel else 1
    voxel = max(voxel, binning * pixel)
    pairs = g.det_cols // binning
    flat = vec[:, [0, 1, 3, 4, 6, 7]].copy()
    flat[:, 2:4] -= 0.5 * (g.det_cols - binning * pairs) * flat[:, 4:6]  # the centre of the columns used
    flat[:, 4:6] *= binning
    n = max(8, int(round((extent[1] - extent[0]) / voxel)))
    xy = tuple(extent[:4])
    positive = np.sign(contrast) * np.asarray(data, dtype=np.float32)
    upper = np.float32(abs(contrast))
    height = row_pixel(g)
    out = []
    for row in (0, g.det_rows - 1):
        # the row's centre height and the edge plane on its outer face (ScanGeometry.window's row offset)
        z = float(g.window(row, 0, rows=1, cols=g.det_cols).vectors[0, 5])
        side = 1.0 if z > 0 else -1.0
        slice_geometry = ScanGeometry("parallel_vec", flat, None, pairs)
        sinogram = positive[:, row, :binning * pairs].reshape(len(positive), pairs, binning).mean(axis=2)
        image = reconstruct_2d("bb", sinogram, slice_geometry, (n, n), xy, iterations=EDGE_ITERATIONS,
                               nonneg=True, upper=upper)
        if float(image.max()) < 0.5 * upper:  # no gas at full contrast: nothing cut by this edge
            centres, radii = np.zeros((0, 2)), np.zeros(0)
        else:
            centres, radii = initial_centres(image, xy, detector="dt", contrast=contrast, border_is_background=True)
            # discs narrower than 3 pixels are noise the opening left (a cap one row high and 0.5 mm in radius
            # cuts a disc of 0.11 mm)
            keep = radii >= MIN_DISC_PIXELS * voxel
            centres, radii = centres[keep], radii[keep]
        out.append((z + side * height / 2, side, centres, radii))
    return out


#: A found bubble may reach this many times its initial radius from its centre along the rotation axis
#: (:func:`edge_centres`): an elongated bubble whose top the edge cuts reaches past its radius, and at 1.0 it
#: would get a second seed.
HALF_HEIGHT_OVER_RADIUS = 1.5


def edge_centres(centres, radii, edges, radius):
    """Centres of the bubbles that edge discs add: the discs no found bubble accounts for.

    A disc (centre ``p``, radius ``rho``) on the edge plane ``z = h`` is
    accounted for when a found bubble (centre ``c``, radius ``r``) may cut the
    plane (``|c_z - h|`` below :data:`HALF_HEIGHT_OVER_RADIUS` times the larger
    of ``r`` and ``radius``) and its centre lies within ``rho`` of ``p`` across. Otherwise
    a sphere of ``radius`` with that disc as its section is placed beyond the
    plane, its centre at ``h + outward sqrt(radius^2 - rho^2)`` (on the plane
    for a disc wider than the sphere), so that its visible part is the cap the
    disc bounds.

    Parameters
    ----------
    centres : (n, 3) float
    radii : (n,) float
        The found bubbles, mm.
    edges : list of (plane, outward, centres, radii)
        :func:`edge_slices`.
    radius : float
        Radius of the added spheres, mm.

    Returns
    -------
    (k, 3) float
    """
    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    radii = np.asarray(radii, dtype=float)
    added = []
    for plane, outward, discs, rho in edges:
        # the found spheres' radii are the common one capped at half the nearest centre's distance, short of an
        # elongated or large bubble's half-height: a bubble within 1.5 times its radius of the plane may cut it
        reach = HALF_HEIGHT_OVER_RADIUS * np.maximum(radii, radius)
        cuts = np.abs(centres[:, 2] - plane) < reach if len(centres) else np.zeros(0, bool)
        near = centres[cuts, :2]
        for p, rk in zip(np.asarray(discs).reshape(-1, 2), rho):
            if len(near) and np.min(np.linalg.norm(near - p, axis=1)) <= rk:
                continue
            lift = np.sqrt(max(radius ** 2 - rk ** 2, 0.0))
            added.append((p[0], p[1], plane + outward * lift))
    return np.array(added, dtype=float).reshape(-1, 3)
