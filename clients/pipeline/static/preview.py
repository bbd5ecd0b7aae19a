"""The voxel preview: a low-resolution voxel reconstruction of the bubbles, from which the
initial bubble centres and radii are chosen (:mod:`.initial`) and the topology rounds
(:mod:`.topology`) find missing bubbles.

- :func:`preview_grid`, :func:`preview_voxel_size`: the grid, the field of view at 256
  (2D, voxels no finer than a detector pixel) or 160 (3D) voxels across.
- :func:`voxel_for_bubbles`: a finer voxel where the bubbles are few voxels across.
- :func:`voxel_preview`: box-constrained projected gradient (default) or SIRT.
- :func:`resample_image`: a voxel image onto another grid (coarse-to-fine preview,
  topology rounds).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from bubsub.core.voxel.astra2d import reconstruct_2d
from bubsub.core.voxel.grid import VoxelGrid, index_to_world, world_to_index
from bubsub.core.voxel.reconstruct3d import reconstruct_3d

from bubsub.clients.pipeline.inputs.fov import field_of_view
from bubsub.clients.pipeline.static.resolution import pixels_per_mm
from bubsub.clients.progress import phase

__all__ = ["axis_pixel", "PREVIEW_FINE_ITERATIONS_3D", "BUBBLE_VOXELS", "MIN_BUBBLE_VOXELS", "MAX_PREVIEW_VOXELS",
           "preview_voxel_size", "preview_grid", "voxel_for_bubbles", "voxel_preview", "resample_image"]


def axis_pixel(geometry):
    """A detector pixel's size at the rotation axis, mm (the finest voxel a preview is made on)."""
    return 1.0 / float(pixels_per_mm(geometry, np.zeros((1, geometry.ndim)))[0])


def preview_voxel_size(geometry):
    """Default voxel size of the preview (mm): the field of view over 256 (2D) or 160 (3D) voxels, in 2D
    no finer than a detector pixel at the axis.

    A 2D preview runs all its iterations on this grid. On voxels finer than the
    pixels that the data resolve, the box-constrained solution of noisy data
    is speckled (a bubble's interior a scatter of dots at 0 and
    ``|contrast|``), and its Otsu mask breaks each bubble into pieces that the
    distance transform seeds one by one: a prepared raw scan of 8 bubbles
    (``bubsub bench fov --inside 0``: 114 columns, 60 views) got 38 seeds on
    voxels of 0.44 pixels and 8 on voxels of a pixel
    (tests/test_preview_pixel.py: 12 bubbles, 110 columns). A 3D preview runs
    all but :data:`PREVIEW_FINE_ITERATIONS_3D` iterations on voxels twice as
    large, and its grid stays.

    Parameters
    ----------
    geometry : ScanGeometry

    Returns
    -------
    float
        mm.
    """
    voxel = 2 * field_of_view(geometry)[0] / (160 if geometry.ndim == 3 else 256)
    if geometry.ndim == 3:
        return voxel
    return max(voxel, axis_pixel(geometry))


def preview_grid(geometry, voxel_size=None, extend=1.0):
    """The voxel preview's grid: the field of view at ``voxel_size`` (default :func:`preview_voxel_size`),
    its radius times ``extend`` (:func:`bubsub.clients.pipeline.inputs.fov.preview_extension`).

    Returns
    -------
    bubsub.core.voxel.grid.VoxelGrid
        ``(shape, extent)``: ``(n, n)`` or ``(slices, n, n)``, extent in mm centred on the axis.
    """
    r_xy, half_z = field_of_view(geometry)
    if voxel_size is None:
        voxel_size = preview_voxel_size(geometry)
    n = max(8, int(np.ceil(2 * extend * r_xy / voxel_size)))
    half = n * voxel_size / 2
    if geometry.ndim == 2:
        return VoxelGrid((n, n), (-half, half, -half, half))
    nz = max(4, int(np.ceil(2 * half_z / voxel_size)))
    hz = nz * voxel_size / 2
    return VoxelGrid((nz, n, n), (-half, half, -half, half, -hz, hz))


#: Voxels across the median bubble that :func:`voxel_for_bubbles` asks for: enough for the distance
#: transform to keep touching bubbles apart, so that nearly every bubble gets one seed (docs/scale.md).
BUBBLE_VOXELS = 9.0

#: Below this many voxels across the median bubble, :func:`voxel_for_bubbles` makes the preview finer.
MIN_BUBBLE_VOXELS = 7.0

#: The most voxels :func:`voxel_for_bubbles` gives a preview (128 MiB a float32 image; the solver holds a few).
MAX_PREVIEW_VOXELS = 2 ** 25


def voxel_for_bubbles(radii, geometry, voxel, extend=1.0):
    """A finer preview voxel (mm) when the median bubble is fewer than :data:`MIN_BUBBLE_VOXELS` voxels
    across, else None.

    The preview's voxel follows the field of view, not the bubbles: where the median bubble is only a few
    voxels across, touching bubbles fuse in it and many get no seed; at :data:`BUBBLE_VOXELS` voxels across
    nearly all get one each, for a small share of the run's time (``bubsub bench scale``'s ~2400-bubble
    column, docs/scale.md). The voxel asked for is no finer than a detector pixel at the axis and keeps the grid within
    :data:`MAX_PREVIEW_VOXELS`.

    Parameters
    ----------
    radii : (n,) float
        The bubbles' radii, mm (seeds of a preview at ``voxel``, or known bubbles).
    geometry : ScanGeometry
    voxel : float
        The preview's voxel, mm.
    extend : float
        As :func:`preview_grid`.

    Returns
    -------
    float or None
    """
    radii = np.asarray(radii, dtype=float)
    radii = radii[np.isfinite(radii) & (radii > 0)]
    if radii.size == 0:
        return None
    across = 2 * float(np.median(radii)) / voxel
    if across >= MIN_BUBBLE_VOXELS:
        return None
    finer = max(voxel * across / BUBBLE_VOXELS, axis_pixel(geometry))
    count = np.prod(preview_grid(geometry, finer, extend).shape, dtype=float)
    if count > MAX_PREVIEW_VOXELS:
        finer *= (count / MAX_PREVIEW_VOXELS) ** (1.0 / geometry.ndim)
    return finer if finer < 0.99 * voxel else None


PREVIEW_FINE_ITERATIONS_3D = 5  # of the 3D preview's iterations, those on the requested grid (the rest on a 2x coarser one)


def voxel_preview(data, geometry, contrast, voxel_size=None, iterations=None, *, progress=False, method="box",
                  coarse_3d=True, extend=1.0):
    """Low-resolution voxel reconstruction of the bubbles, for the initialisation.

    The bubble data ``sign(contrast) * data`` is the projection of an image
    that is ``|contrast|`` inside bubbles and 0 elsewhere. ``method="box"``
    (default) uses both bounds: projected gradient descent with
    Barzilai-Borwein steps (:func:`bubsub.core.voxel.solvers.pgd_bb`) onto
    ``0 <= x <= |contrast|`` (50 iterations in 2D, 30 in 3D); at few views it
    separates touching bubbles that SIRT blurs together (README example, 13
    views: the 40 bubbles seeded instead of 34; docs/robustness.md).
    ``method="sirt"``: SIRT with ``x >= 0`` only (100 iterations in 2D, 15 in 3D).
    ``extend`` widens the grid beyond the field of view's radius by that
    factor (:func:`bubsub.clients.pipeline.inputs.fov.preview_extension`), so that
    bubbles partly outside the reconstructable cylinder, which some
    projections see, have voxels to go to.

    Parameters
    ----------
    data : ndarray, ``(angles, cols)`` or ``(angles, rows, cols)``
        Line integrals of the scan (``scan.bubble_data``).
    geometry : bubsub.core.ScanGeometry
        Of ``data``.
    contrast : float
        Bubble contrast (1/mm, ``scan.bubble_contrast``); its sign says whether bubbles are darker.
    voxel_size : float, optional
        Of the preview (mm); default :func:`preview_voxel_size`.
    iterations : int, optional
        Default: 50 (box, 2D), 30 (box, 3D), 100 (SIRT, 2D), 15 (SIRT, 3D).
    progress : bool
        Show the iterations as a phase.
    method : {"box", "sirt"}
    coarse_3d : bool
        In 3D, run all but :data:`PREVIEW_FINE_ITERATIONS_3D` iterations on a 2x coarser grid.
    extend : float
        Grid radius over the field of view's radius (>= 1).

    Returns
    -------
    image : ndarray float32, ``(rows, cols)`` or ``(slices, rows, cols)``
        Bubble "density" (``|contrast|`` inside bubbles, 0 elsewhere).
    extent : tuple
        ``(xmin, xmax, ymin, ymax[, zmin, zmax])`` in mm.
    """
    if method not in ("box", "sirt"):
        raise ValueError(f"preview method must be 'box' or 'sirt', got {method!r}")
    shape, extent = preview_grid(geometry, voxel_size, extend)
    positive = np.sign(contrast) * np.asarray(data, dtype=np.float32)
    box = method == "box"
    upper = np.float32(abs(contrast)) if box else None  # SIRT takes x >= 0 only
    if geometry.ndim == 2 and not box:  # ASTRA's own SIRT: about a second, no per-iteration callback
        with phase("voxel preview (2D SIRT)", 1, unit="reconstruction", enabled=progress) as bar:
            image = reconstruct_2d("sirt", positive, geometry, shape, extent, iterations=iterations or 100,
                                   nonneg=True)
            bar.update(1, voxels="x".join(map(str, shape)))
        return image, extent
    n = iterations or ((50 if box else 100) if geometry.ndim == 2 else (30 if box else 15))

    def step(k, x):
        bar.update(1)

    name = "bb" if box else "sirt"
    label = f"voxel preview ({geometry.ndim}D {'box-constrained BB' if box else 'SIRT'})"
    if geometry.ndim == 2:
        with phase(label, n, enabled=progress) as bar:
            image = reconstruct_2d(name, positive, geometry, shape, extent, iterations=n, nonneg=True, callback=step,
                                   upper=upper)
            bar.postfix["voxels"] = "x".join(map(str, shape))
        return image, extent
    # Coarse to fine: most iterations run on voxels twice as large (8x fewer, so 8x
    # cheaper; on the requested grid alone the 3D preview takes about half of a
    # reconstruction's time), then a few on the requested grid refine the edges.
    fine = min(n, PREVIEW_FINE_ITERATIONS_3D)
    coarse = n - fine if coarse_3d else 0
    x0 = None
    with phase(label, n, enabled=progress) as bar:
        if coarse > 0:
            voxel = (extent[1] - extent[0]) / shape[-1]
            shape_c, extent_c = preview_grid(geometry, 2 * voxel, extend)
            image_c = reconstruct_3d(name, positive, geometry, shape_c, extent_c, iterations=coarse, nonneg=True,
                                     callback=step, upper=upper)
            x0 = resample_image(image_c, extent_c, shape, extent)
        image = reconstruct_3d(name, positive, geometry, shape, extent, iterations=n - coarse, nonneg=True, x0=x0,
                               callback=step, upper=upper)
        bar.postfix["voxels"] = "x".join(map(str, shape))
    return image, extent


def resample_image(image, extent, shape, new_extent):
    """Trilinear (bilinear in 2D) resampling of a voxel image onto another grid (edge values extended).

    Parameters
    ----------
    image : ndarray, ``(rows, cols)`` or ``(slices, rows, cols)``
    extent : tuple
        Of ``image``, mm (grid convention of :mod:`bubsub.core.voxel.grid`).
    shape, new_extent
        The new grid.

    Returns
    -------
    ndarray float32 of ``shape``
    """
    # both grids are axis-aligned, so each new index maps to an old one by a per-axis affine
    # function: found from indices 0 and 1, applied without any coordinate arrays
    nd = len(shape)
    src = world_to_index(index_to_world(np.array([np.zeros(nd), np.ones(nd)]), shape, new_extent), image.shape, extent)
    out = ndimage.affine_transform(np.asarray(image, dtype=np.float32), src[1] - src[0], offset=src[0],
                                   output_shape=tuple(shape), order=1, mode="nearest")
    return out.astype(np.float32, copy=False)
