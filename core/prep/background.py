"""The stationary background: everything in the projections that is not a bubble.

Two estimates, both per detector row (so they stream in row slabs):

* :func:`envelope_background`: for a background that is rotation-invariant
  (a container and its liquid centred on the rotation axis), the projection
  of the background is the same at every angle, and bubbles (gas, less
  attenuating) only lower the line integrals. The background of a detector
  pixel is the upper envelope of its values over the angles: the angles
  whose (column-smoothed) value lies within two noise levels of the 95th
  percentile are averaged, unsmoothed, so the estimate is not biased
  upward by the noise.
* :func:`radial_background` (``auto``), also for a rotation-invariant
  background but robust where every angle's ray crosses a bubble: a
  filtered back-projection of the row, and per ring about the axis the
  mean of its dense (liquid, wall) pixels (:func:`dense_and_gas_masks`), which makes a
  radial profile of the container and liquid, projected again.
* :func:`chord_background` (``auto`` where a row has no air at its sides,
  :func:`sees_air`: a liquid cylinder wider than the detector, local
  tomography): the liquid's chord profile ``mu * 2 sqrt(R^2 - s^2)``, fitted
  to the mean projection over the angles less the gas that a reconstruction
  of the field of view shows there; its radius fitted, or given (the
  container's), and then the foam beyond the field of view's own gas
  fraction fitted with it.
* :func:`reproject_background` (the paper's route, for any background): a
  filtered back-projection of the row, the foam region (a disc around the
  axis) set to the liquid attenuation, projected again.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage.filters import threshold_otsu

from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.voxel.astra2d import AstraProjector2D, reconstruct_2d

__all__ = ["fbp_row", "row_geometry", "row_phases", "detector_offsets", "envelope_background", "radial_background", "reproject_background",
           "liquid_and_gas", "noise_level", "sees_air", "chord_background", "foam_beyond", "FOAM_BEYOND_REACH",
           "NO_AIR_LEVEL"]


def noise_level(block):
    """Robust per-value noise of line integrals ``(n_angles, ..., cols)``, from differences of adjacent columns."""
    d = np.diff(np.asarray(block, dtype=np.float32), axis=-1)
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0))


def envelope_background(block, *, percentile=95.0, smooth=2.0):
    """Rotation-invariant background of a block of line integrals.

    Parameters
    ----------
    block : (n_angles, rows, cols) or (n_angles, cols) float
    percentile : float
        Envelope percentile over the angles.
    smooth : float
        Gaussian sigma along the columns (pixels) for choosing the angles.

    Returns
    -------
    ndarray float32, ``block.shape[1:]``
        The background of every detector pixel (the same at every angle).
    """
    b = np.asarray(block, dtype=np.float32)
    sm = ndimage.gaussian_filter1d(b, smooth, axis=-1, mode="nearest") if smooth else b
    sigma = noise_level(b) / np.sqrt(2 * np.sqrt(np.pi) * max(smooth, 0.5))
    env = np.percentile(sm, percentile, axis=0)
    keep = sm >= env[None] - 2.0 * sigma
    n = keep.sum(axis=0)
    return (np.where(keep, b, 0.0).sum(axis=0) / np.maximum(n, 1)).astype(np.float32)


def dense_and_gas_masks(image, mask, *, sigma=2.0, erode=2):
    """Liquid (dense) and gas pixels of a noisy slice inside ``mask``.

    Pixels are classified on a Gaussian-smoothed copy (Otsu's threshold) and
    the masks eroded away from the interfaces, so that averaging the
    *unsmoothed* values over each mask is neither biased by the noise (as
    thresholding the noisy values would be) nor by blurred edges.
    """
    sm = ndimage.gaussian_filter(np.asarray(image, dtype=np.float32), sigma)
    t = threshold_otsu(sm[mask])
    dense = ndimage.binary_erosion(sm > t, iterations=erode) & mask
    gas = ndimage.binary_erosion(sm <= t, iterations=erode) & mask
    return dense, gas


def liquid_and_gas(image, mask, erode=2):
    """Liquid and gas attenuation (1/mm) of a reconstructed slice inside ``mask``.

    The means of the two phases of :func:`dense_and_gas_masks` (the liquid
    is the denser one), each eroded by ``erode`` pixels from the interfaces.
    """
    dense, gas = dense_and_gas_masks(image, mask, erode=erode)
    if dense.sum() < 16 or gas.sum() < 16:
        raise ValueError("too few liquid or gas pixels in the foam region to estimate their attenuation; "
                         "pass --contrast")
    return float(np.mean(image[dense])), float(np.mean(image[gas]))


def reproject_background(sinogram, geometry, foam_radius, *, liquid=None, grid=None):
    """The paper's background: FBP, foam disc set to the liquid, forward projection.

    Parameters
    ----------
    sinogram : (n_angles, cols) float
        Line integrals of one detector row.
    geometry : ScanGeometry
        2D (``parallel_vec``) geometry of the row, axis at the origin.
    foam_radius : float
        Radius of the foam region around the axis, mm.
    liquid : float, optional
        Liquid attenuation, 1/mm; default from the slice (:func:`liquid_and_gas`).
    grid : int, optional
        Reconstruction pixels across the field of view (default ``cols``).

    Returns
    -------
    background : (n_angles, cols) float32
    liquid, gas : float
        Attenuations used / found, 1/mm.
    """
    image, extent, r, _ = fbp_row(sinogram, geometry, grid)
    foam = r <= foam_radius
    lq, gas = liquid_and_gas(image, foam)
    liquid = lq if liquid is None else float(liquid)
    bg = _reproject(np.where(foam, liquid, image), geometry, extent)
    return bg, liquid, gas


def fbp_row(sinogram, geometry, grid=None):
    """FBP of one row over the square the detector spans: ``image, extent, radius of each pixel, pixel size``."""
    cols = geometry.det_count
    pixel = float(np.linalg.norm(geometry.vectors[0, 4:6]))
    n = grid or cols
    half = 0.5 * cols * pixel
    extent = (-half, half, -half, half)
    image = reconstruct_2d("fbp", np.asarray(sinogram, dtype=np.float32), geometry, (n, n), extent)
    centres = (np.arange(n) + 0.5) * (2 * half / n) - half
    return image, extent, np.hypot(centres[None, :], centres[:, None]), 2 * half / n


def row_geometry(geometry):
    """The 2D geometry of one detector row of a parallel 3D geometry (same angles and axis); a 2D one as it is."""
    if geometry.ndim == 2:
        return geometry
    v = geometry.vectors
    return ScanGeometry.from_astra("parallel_vec", v[:, [0, 1, 3, 4, 6, 7]], det_count=geometry.det_cols)


def row_phases(sinogram, geometry, foam_radius=None):
    """Liquid and gas attenuation (1/mm) of one row: :func:`liquid_and_gas` of its FBP (at most 512 pixels
    across) inside ``foam_radius`` mm of the axis (default 0.9 of the detector's half-width).

    Raises
    ------
    ValueError
        From :func:`liquid_and_gas`, where either phase has too few pixels.
    """
    image, extent, r, _ = fbp_row(sinogram, geometry, min(geometry.det_count, 512))
    return liquid_and_gas(image, r <= (foam_radius or 0.9 * extent[1]))


def _reproject(image, geometry, extent):
    with AstraProjector2D(geometry, image.shape, extent) as op:
        return op.forward(image.astype(np.float32)).reshape(geometry.shape).astype(np.float32)


def detector_offsets(geometry):
    """Signed distance (mm) of each detector column's centre from the rotation axis, 2D parallel geometry."""
    v = geometry.vectors[0]
    u = v[4:6]
    pixel = float(np.linalg.norm(u))
    axis = geometry.det_count / 2 - 0.5 - float(np.dot(v[2:4], u)) / pixel ** 2
    return (np.arange(geometry.det_count) - axis) * pixel


def radial_background(sinogram, geometry, *, min_fraction=0.2, smooth=1.5, grid=256, max_angles=128):
    """Rotation-invariant background of one row from ring means of its reconstruction.

    The ring profile is projected analytically (each ring is an annulus of
    constant attenuation, whose chord lengths are exact), so the result is
    the same at every angle.

    Parameters
    ----------
    sinogram, geometry
        One detector row and its 2D geometry, as for :func:`reproject_background`.
    min_fraction : float
        Rings with fewer dense pixels than this fraction take the dense
        value of their neighbours (inside the sample: rings mostly filled by
        bubbles) or are averaged whole (beyond the outermost dense ring: air).
    smooth : float
        Gaussian sigma of the profile, rings.
    grid : int
        At most this many reconstruction pixels across the detector.
    max_angles : int
        At most this many projections (every k-th, so still spread over the
        whole rotation) enter the FBP. The profile is a mean over rings of
        hundreds of pixels, which averages the noise and the streaks of a
        coarse, sparser FBP out: with 256 pixels and at most 128 angles the
        background is as accurate as with 512 pixels and every angle
        (mean error 0.0028 against 0.0043 over a simulated foam's columns,
        360 angles x 997 columns) at a seventh of the CPU time (0.14 s
        against 0.99 s per row; ``python -m bubsub.bench prepare
        --background-rows``, docs/prepare.md).

    Returns
    -------
    (cols,) float32
        The background of each detector column (at every angle).
    """
    step = -(-geometry.n_angles // max_angles)
    image, extent, r, pix = fbp_row(np.asarray(sinogram)[::step], geometry[::step], min(grid, geometry.det_count))
    inside = r <= extent[1]
    dense, _ = dense_and_gas_masks(image, inside)
    ring = np.minimum((r / pix).astype(int), int(extent[1] / pix))
    nring = ring.max() + 1
    n_all = np.bincount(ring[inside], minlength=nring)
    n_dense = np.bincount(ring[dense], minlength=nring)
    s_all = np.bincount(ring[inside], weights=image[inside], minlength=nring)
    s_dense = np.bincount(ring[dense], weights=image[dense], minlength=nring)
    use = (n_dense >= min_fraction * np.maximum(n_all, 1)) & (n_dense > 0)
    profile = s_all / np.maximum(n_all, 1)  # beyond the sample: air, all of the ring
    if use.any():
        k = np.arange(nring)
        last = int(k[use].max())
        # inside the sample, rings that are mostly gas take the liquid of their neighbours
        profile[: last + 1] = np.interp(k[: last + 1], k[use], (s_dense / np.maximum(n_dense, 1))[use])
    profile = ndimage.gaussian_filter1d(profile, smooth, mode="nearest") if smooth else profile
    edges = np.arange(nring + 1) * pix
    s = detector_offsets(geometry)
    chords = 2 * np.sqrt(np.maximum(edges[:, None] ** 2 - s[None, :] ** 2, 0))  # (nring + 1, cols)
    return (profile[:, None] * np.diff(chords, axis=0)).sum(axis=0).astype(np.float32)


#: A row has no air beside its sample (a container wider than the detector) when the mean over the angles of
#: its outermost columns stands above this fraction of the mean projection's peak on both sides.
NO_AIR_LEVEL = 0.1


def sees_air(sinogram, level=NO_AIR_LEVEL, side=4):
    """Whether a row's mean projection falls to air on at least one side of the detector.

    Parameters
    ----------
    sinogram : (n_angles, cols) float
        Line integrals of one detector row.

    Returns
    -------
    bool
        False when both sides' ``side`` outermost columns average above
        ``level`` times the mean projection's peak (the sample is wider
        than the detector).
    """
    m = np.asarray(sinogram, dtype=float).mean(axis=0)
    peak = float(m.max())
    return not (peak > 0 and min(m[:side].mean(), m[-side:].mean()) > level * peak)


#: Passes of :func:`chord_background`'s second step, each from the previous one's profile (on the simulated scans
#: of ``python -m bubsub.bench fov --local``, seeds 0-5, the second pass moves the liquid's projection at the axis
#: by 0.005 at most, a third by 0.001).
REFINE_PASSES = 2


def _fit_chord(profile, s, radius_from):
    """Least-squares ``A * 2 sqrt(R^2 - s^2)`` to ``profile``: ``(R, A, chord)``, ``R`` from ``radius_from`` to ten times it."""
    best = None
    for radius in radius_from * np.geomspace(1.0 + 1e-3, 10.0, 400):
        chord = 2 * np.sqrt(radius * radius - s * s)
        a = float(profile @ chord / (chord @ chord))
        err = float(np.sum((profile - a * chord) ** 2))
        if best is None or err < best[0]:
            best = (err, radius, a, chord)
    return best[1:]


def chord_background(sinogram, geometry, *, grid=256, max_angles=128, erode=2, radius=None):
    """Background of a row whose rotation-invariant liquid cylinder is wider than the detector.

    The liquid's projection is ``mu c_R(s)``, ``c_R(s) = 2 sqrt(R^2 - s^2)``
    at the distance ``s`` from the axis, the same at every angle. The mean
    projection over the angles adds the bubbles' mean gas chord times the
    contrast ``C``: ``m(s) = mu c_R(s) + C g(s)``. Two passes:

    1. ``A c_R`` fitted to ``m`` (least squares, ``R`` searched from the
       detector's half-width to ten times it), as if the gas were spread
       evenly over the cylinder; removing it removes the truncated sample's
       large smooth part, so that a filtered back-projection of the rest
       shows the liquid and the gas without the cupping of local tomography.
    2. That reconstruction, split into gas and liquid (Otsu's threshold on
       a Gaussian-smoothed copy), gives the gas inside the field of view's
       disc (radius ``r_f``, chord ``c_f``) itself: its projection's mean
       over the angles ``g_in(s)``, its area fraction ``phi``, and ``C``
       (the means of the eroded phases, :func:`dense_and_gas_masks`). Only
       the foam beyond the disc is modelled, with the same gas fraction
       out to the wall: ``m - C g_in + C phi c_f = (mu + C phi) c_R``,
       fitted again for ``R`` and ``mu``.

    With the liquid's ``radius`` given (the container's inner radius), the
    foam beyond the disc has a gas fraction of its own, ``phi_o``:
    ``m - C g_in = mu c_R + C phi_o (c_R - c_f)``, linear in ``mu`` and
    ``phi_o``, fitted by least squares (the first pass fits ``A c_R``).

    The first pass alone takes the bubbles' chance arrangement inside the
    field of view for the liquid's profile; on the simulated scans of
    ``python -m bubsub.bench fov --local`` (seeds 0-5, the axis found) it misses the
    liquid's projection at the axis (0.44 there) by -0.013 to +0.052, the
    second step (:data:`REFINE_PASSES` passes) by -0.002 to +0.008 on five
    of them and by +0.058 on the sixth, whose foam beyond the field of view
    holds 0.64 times the gas fraction of the foam inside it (0.75-0.85 on
    the others and on seeds 6 and 7: no bubble crosses the wall, and the
    foam thins towards it). What the mean projection does
    not tell apart is the liquid's radius from a gas fraction that changes
    beyond the field of view: with ``phi_o`` free, radii 5 % apart leave
    the same residual of the mean projection (within 5 % on those six scans
    and two more) and liquids' projections 0.03 apart at the axis. Given
    the radius, the fit misses the liquid's projection at the axis by
    -0.013 to +0.013 on all eight, and its curvature (the error at the
    outermost columns less that at the axis) by 0.003 at most; given 5 %
    off, by 0.011 at most (``python -m bubsub.bench fov --local-background
    0 1 2 3 4 5 6 7``).

    Parameters
    ----------
    sinogram : (n_angles, cols) float
    geometry : ScanGeometry
        2D parallel geometry of the row, axis at the origin.
    grid, max_angles
        As for :func:`radial_background`.
    erode : int
        Pixels the phases' masks of ``C`` are eroded by from the interfaces.
    radius : float, optional
        The liquid cylinder's radius, mm (the container's inner radius);
        default fitted.

    Returns
    -------
    background : (cols,) float32
        The liquid's projection at each column (every angle).
    fit : dict
        ``radius_mm`` and ``liquid_attenuation`` (``mu``, 1/mm) of the
        liquid, ``mean_attenuation`` (``A`` of the first pass),
        ``gas_fraction`` (``phi``), ``outer_gas_fraction`` (``phi_o``;
        ``phi`` where the radius is fitted), ``contrast`` (``C``, 1/mm) and
        ``residual_rms``, the root mean square of ``m`` less its model.

    Raises
    ------
    ValueError
        If ``radius`` does not exceed the distance of the detector's
        farthest column from the axis.
    """
    sino = np.asarray(sinogram, dtype=np.float64)
    s = detector_offsets(geometry)
    m = sino.mean(axis=0)
    half = float(np.abs(s).max())
    given = radius is not None
    if not given:
        radius, a, chord = _fit_chord(m, s, half)
    elif not radius > half:
        raise ValueError(f"the liquid's radius {radius} mm does not exceed the detector's reach from the axis "
                         f"({half:.4g} mm): give the container's inner radius (--liquid-radius, mm) or leave it out to fit it")
    else:
        chord = 2 * np.sqrt(radius * radius - s * s)
        a = float(m @ chord / (chord @ chord))
    step = -(-geometry.n_angles // max_angles)
    sub = geometry[::step]
    r_f = float(min(-s[0], s[-1]))
    c_f = 2 * np.sqrt(np.maximum(r_f * r_f - s * s, 0.0))
    fit = {"radius_mm": float(radius), "mean_attenuation": a, "liquid_attenuation": a, "gas_fraction": 0.0,
           "outer_gas_fraction": 0.0, "contrast": 0.0, "residual_rms": float(np.sqrt(np.mean((m - a * chord) ** 2)))}
    for _ in range(REFINE_PASSES):
        rest = (sino - a * chord[None])[::step].astype(np.float32)
        image, extent, r, _ = fbp_row(rest, sub, min(grid, geometry.det_count))
        region, disc = r <= 0.9 * extent[1], r <= r_f
        dense, gas_core = dense_and_gas_masks(image, region, erode=erode)
        if not dense.any() or not gas_core.any():  # no foam to see: the liquid alone
            mu = a + (float(np.mean(image[dense])) if dense.any() else 0.0)
            return (mu * chord).astype(np.float32), {**fit, "liquid_attenuation": float(mu)}
        contrast = float(np.mean(image[gas_core]) - np.mean(image[dense]))
        smooth = ndimage.gaussian_filter(image, 1.0)
        gas = (smooth <= threshold_otsu(smooth[region])) & disc
        phi = float(gas.sum() / disc.sum())
        g_in = _reproject(gas.astype(np.float32), sub, extent).mean(axis=0)  # mm of gas, per column
        if given:  # the liquid and the outer foam's own gas fraction, linear in both
            (mu, phi_o), *_ = np.linalg.lstsq(np.stack([chord, contrast * (chord - c_f)], axis=1),
                                              m - contrast * g_in, rcond=None)
            mu, phi_o = float(mu), float(phi_o)
            a = mu + contrast * phi_o  # the cylinder's mean attenuation, taken out before the next pass's FBP
        else:
            radius, a, chord = _fit_chord(m - contrast * g_in + contrast * phi * c_f, s, half)
            mu, phi_o = a - contrast * phi, phi
        model = mu * chord + contrast * (g_in + phi_o * (chord - c_f))  # the mean projection's model
        fit = {"radius_mm": float(radius), "mean_attenuation": fit["mean_attenuation"], "liquid_attenuation": mu,
               "gas_fraction": phi, "outer_gas_fraction": phi_o, "contrast": contrast,
               "residual_rms": float(np.sqrt(np.mean((m - model) ** 2)))}
    return (fit["liquid_attenuation"] * chord).astype(np.float32), fit


#: Field-of-view radii beyond which :func:`foam_beyond` takes the foam into the background. The reconstruction
#: fits bubbles out to 1.25 of them (``bubsub.clients.pipeline.inputs.fov.LOCAL_EXTEND``), and those cut by that
#: circle reach a bubble further: from 1.25, seeds 11 and 56 of ``python -m bubsub.bench fov --local`` gained 2 and
#: 4 spurious bubbles, and the wider foam's DDI rose on three of four seeds (docs/prepare.md, ``--local-reach``).
FOAM_BEYOND_REACH = 1.5


def foam_beyond(fit, geometry, reach=None):
    """The mean projection over the angles of the foam beyond ``reach`` field-of-view radii, as
    :func:`chord_background` models it: its gas fraction ``phi_o`` spread evenly out to the liquid's wall.

    The reconstruction of a local-tomography scan fits the bubbles within and around the field of view; those
    further out are each seen by a few projections only and are left to the fit's residual. Their mean over the
    projections, ``C phi_o (c_R(s) - c_X(s))`` (``c_X`` the chord of the disc of ``reach`` field-of-view
    radii), is the same in every projection, and left in the data it reads, in a reconstruction of the field of
    view, as gas spread over the liquid (which is what the preview seeds the bubbles from). The mean projection
    does not tell the liquid's radius from the outer foam's gas fraction (:func:`chord_background`): where the
    fitted radius is too large, ``mu c_R`` is too high by what the too large outer foam here takes away again,
    so the liquid and this together are what the data fix (:func:`bubsub.bench.fov_local.local_background_case`).

    Parameters
    ----------
    fit : dict
        :func:`chord_background`'s: ``radius_mm``, ``contrast``, ``outer_gas_fraction``.
    geometry : ScanGeometry
        2D parallel geometry of the row, axis at the origin.
    reach : float, optional
        Field-of-view radii from which the foam is taken (> 1; ``inf``: none); default
        :data:`FOAM_BEYOND_REACH` (read at the call).

    Returns
    -------
    (cols,) float32
        0 where the liquid's wall lies within ``reach`` field-of-view radii.
    """
    reach = FOAM_BEYOND_REACH if reach is None else reach
    if not reach > 1:
        raise ValueError(f"reach must exceed the field of view's radius (1), got {reach!r}")
    s = detector_offsets(geometry)
    r_x = reach * float(min(-s[0], s[-1]))
    radius = float(fit["radius_mm"])
    if radius <= r_x:
        return np.zeros(len(s), dtype=np.float32)
    outer = 2 * np.sqrt(radius * radius - s * s) - 2 * np.sqrt(r_x * r_x - s * s)
    return (fit["contrast"] * fit["outer_gas_fraction"] * outer).astype(np.float32)
