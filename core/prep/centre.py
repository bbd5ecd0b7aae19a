"""Rotation-axis search for parallel-beam scans.

* :func:`center_vo`: Vo et al. (2014)'s Fourier method on a 180-degree
  sinogram, as implemented by algotom (``find_center_vo``).
* :func:`center_symmetry`: the mean projection over the angles of a
  rotation-invariant sample (a liquid cylinder filled with foam) is
  symmetric about the axis; needs no air at the sides (local tomography).
* :func:`center_pair`: a projection and its mirror image taken 180 degrees
  later are reflections of each other about the axis; their registration
  shift (scikit-image's sub-pixel phase correlation) gives the axis column.
* :func:`center_seam`: mirrored about the axis, a 180-degree sinogram
  continues its last rows smoothly.
* :func:`center_sharpness`: refines a column found by the others: the
  filtered back-projection with the least total variation.
* :func:`center_sharpest`: the same criterion over the whole middle of the
  detector, coarser; needs neither air at the sides nor a 180-degree seam.

Columns are detector pixel indices (pixel ``j`` has its centre at ``j``),
so the axis of a centred detector is at ``(cols - 1) / 2``.
"""

from __future__ import annotations

import warnings

import numpy as np
from skimage.registration import phase_cross_correlation

from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.voxel.astra2d import reconstruct_2d

__all__ = ["center_vo", "center_pair", "closest_pair", "center_symmetry", "center_seam", "center_sharpness",
           "center_sharpest"]


def center_vo(sinogram):
    """Axis column of a 180-degree sinogram ``(n_angles, cols)`` of line integrals (algotom)."""
    from algotom.prep.calculation import find_center_vo

    sino = np.asarray(sinogram, dtype=np.float32)
    if sino.ndim != 2 or sino.shape[0] < 8:
        raise ValueError(f"the centre search needs a (n_angles >= 8, cols) sinogram, got shape {sino.shape}")
    cols = sino.shape[1]
    # search the middle half of the detector (algotom's default is the middle eighth)
    return float(find_center_vo(sino, start=cols * 0.25, stop=cols * 0.75, step=0.25, ncore=1))


def closest_pair(theta_deg):
    """The two projections whose angles differ by the closest to 180 degrees.

    Returns
    -------
    i, j : int
    error : float
        ``|theta[j] - theta[i] - 180|``, degrees.
    """
    t = np.asarray(theta_deg, dtype=float)
    diff = np.abs(np.abs(t[None, :] - t[:, None]) - 180.0)
    i, j = np.unravel_index(np.argmin(diff), diff.shape)
    i, j = (i, j) if t[i] < t[j] else (j, i)
    return int(i), int(j), float(diff[i, j])


def center_pair(p0, p180):
    """Axis column from two projections 180 degrees apart.

    Parameters
    ----------
    p0, p180 : (rows, cols) or (cols,) float
        Line integrals (flat-corrected, ``-log``).

    Returns
    -------
    float
        Axis column (pixel index units).
    """
    a, b = np.atleast_2d(np.asarray(p0, dtype=float)), np.atleast_2d(np.asarray(p180, dtype=float))
    if a.shape != b.shape:
        raise ValueError(f"the two projections differ in shape: {a.shape} and {b.shape}")
    # a feature at column c + s in p0 sits at c - s in p180, i.e. at cols - 1 - c + s once p180 is mirrored
    shift, _, _ = phase_cross_correlation(a, b[:, ::-1], upsample_factor=20, normalization=None)
    return 0.5 * (a.shape[1] - 1 + float(shift[-1]))


def center_symmetry(sinogram, *, search=(0.25, 0.75), step=0.05):
    """Axis column about which the mean projection over the angles is most symmetric.

    A container and its liquid centred on the axis project the same at
    every angle, symmetric about the axis, and a foam filling it adds a
    mean over the angles that is symmetric too up to the few bubbles'
    differences; the sample's edges need not be on the detector (a sample
    wider than it, local tomography, where the Fourier method and a mirrored
    pair need air at the sides). For each candidate ``c`` the mean
    projection ``m`` is compared with its mirror image about ``c``, ``m(c +
    x)`` against ``m(c - x)`` (linear interpolation) over the widest ``x``
    both sides hold, by their mean squared difference relative to ``m``'s
    variance there; the least, refined by a parabola through it and its
    neighbours, is the axis.

    Parameters
    ----------
    sinogram : (n_angles, cols) float
        Line integrals of one detector row (180 or 360 degrees).
    search : (float, float)
        Fractions of the detector width searched.
    step : float
        Candidate spacing, pixels.

    Returns
    -------
    float
        Axis column (pixel index units).
    """
    sino = np.asarray(sinogram, dtype=float)
    if sino.ndim != 2 or sino.shape[0] < 2:
        raise ValueError(f"the centre search needs a (n_angles, cols) sinogram, got shape {sino.shape}")
    m = sino.mean(axis=0)
    cols = m.size
    k = np.arange(cols, dtype=float)
    cand = np.arange(search[0] * (cols - 1), search[1] * (cols - 1) + step / 2, step)
    cost = np.empty(cand.size)
    for i, c in enumerate(cand):
        half = min(c, cols - 1 - c)
        x = np.arange(0.0, half + 1e-9, 0.5)
        right, left = np.interp(c + x, k, m), np.interp(c - x, k, m)
        both = np.concatenate([right, left])
        cost[i] = np.mean((right - left) ** 2) / max(float(np.var(both)), 1e-30)
    return _least(cand, cost)


def center_seam(sinogram, theta_deg, *, search=(0.25, 0.75), step=0.25):
    """Axis column that joins a 180-degree scan to its mirror image without a seam.

    In a parallel beam the projection at ``theta + 180`` is the one at
    ``theta`` mirrored about the axis column ``c``: ``p(theta + 180, s) =
    p(theta, 2c - s)``. Mirrored about the right ``c``, the sinogram of a
    scan over ``[0, 180)`` continues its own last rows smoothly: the rows
    around each seam (at 180 and at 360 degrees) have second differences
    along the angle as small as anywhere else, while a wrong ``c`` shifts
    the mirrored rows by ``2 (c - c_true)`` pixels. The sum of those second
    differences' squares, over the columns both rows hold (the interior: no
    air at the sides is needed), is least at the axis; it is refined by a
    parabola through the least candidate and its neighbours.

    Parameters
    ----------
    sinogram : (n_angles, cols) float
        Line integrals of one detector row, angles evenly spaced over 180
        degrees less one step (``n_angles >= 4``).
    theta_deg : (n_angles,) float
        The angles, degrees.
    search : (float, float)
        Fractions of the detector width searched.
    step : float
        Candidate spacing, pixels.

    Returns
    -------
    float
        Axis column (pixel index units).

    Raises
    ------
    ValueError
        If the angles are not evenly spaced over 180 degrees less one step.
    """
    sino = np.asarray(sinogram, dtype=float)
    th = np.asarray(theta_deg, dtype=float)
    n, cols = sino.shape
    d = np.diff(th)
    if n < 4 or th.size != n or np.ptp(d) > 0.01 * abs(d[0]) or abs(abs(n * d[0]) - 180.0) > 0.5 * abs(d[0]):
        raise ValueError("the seam centre search needs at least 4 angles evenly spaced over 180 degrees less one step")
    k = np.arange(cols, dtype=float)
    # rows around the seams: S[n-2], S[n-1] | M[0], M[1] and M[n-2], M[n-1] | S[0], S[1]
    cand = np.arange(search[0] * (cols - 1), search[1] * (cols - 1) + step / 2, step)
    cost = np.empty(cand.size)
    for i, c in enumerate(cand):
        src = 2 * c - k
        ok = (src >= 0) & (src <= cols - 1)
        mirror = lambda row: np.interp(src[ok], k, row)
        a = [sino[-2, ok], sino[-1, ok], mirror(sino[0]), mirror(sino[1])]
        b = [mirror(sino[-2]), mirror(sino[-1]), sino[0, ok], sino[1, ok]]
        cost[i] = sum(np.mean((r[0] - 2 * r[1] + r[2]) ** 2) + np.mean((r[1] - 2 * r[2] + r[3]) ** 2) for r in (a, b))
    return _least(cand, cost)


def center_sharpness(sinogram, theta_deg, start, *, width=2.0, step=0.25, max_cols=512, max_angles=256,
                     truncated=False):
    """Axis column near ``start`` whose filtered back-projection has the least total variation.

    A wrong axis smears every feature of the slice into an arc (each
    projection puts it at another place), which adds edges: the total
    variation ``sum |grad f|`` of the reconstruction ``f`` over the disc of
    0.8 times the detector's half-width is least at the axis, down to a
    fraction of a pixel where the searches above, on few projections, are
    off by a pixel (on the raw scans of ``python -m bubsub.bench fov
    --inside``, seeds 0-5, 60 projections: Vo's method, the seam and the
    symmetry each off by up to 1.2 raw pixels, this refinement of the one
    taken within 0.12). Candidates every ``step`` pixels within ``width``
    of ``start``, the least refined by a parabola through it and its
    neighbours. Works without air at the sides too (the interior's edges),
    with ``truncated``: the row of a sample wider than the detector is then
    continued by its edge columns over half its width on each side before
    the FBP, so that the ramp filter does not see the detector's edges as
    the sample's (without it the least total variation of such a row
    follows the truncation, not the axis: tests/test_local_tomography.py).
    The total variation is summed over 0.8 times the continued row's
    half-width, beyond the field of view, where a wrong axis smears the
    features near its edge; it ripples there with a period of about a
    pixel, so the least is that of one parabola fitted to every candidate
    (least squares) instead of the least candidate refined by its
    neighbours (on the raw scans of ``python -m bubsub.bench fov
    --local-axis``, seeds 0-59: within 0.27 raw pixels, where a ripple's
    least lands 0.75 off on seed 16; the window's edge where the total
    variation falls all the way there).

    Parameters
    ----------
    sinogram : (n_angles, cols) float
        Line integrals of one detector row (phase-retrieved where phase
        contrast is strong: its fringes are edges too).
    theta_deg : (n_angles,) float
        The angles, degrees.
    start : float
        The column searched about (pixel index units).
    width, step : float
        Pixels.
    max_cols, max_angles : int
        The row is binned to at most ``max_cols`` columns and at most
        ``max_angles`` projections are back-projected (speed).
    truncated : bool
        The sample is wider than the detector (no air at the row's sides):
        the row is continued by its edge columns (see above).

    Returns
    -------
    float
        Axis column (pixel index units).
    """
    if not truncated:
        cand = np.arange(start - width, start + width + step / 2, step)
        return _least(cand, _total_variations(sinogram, theta_deg, cand, max_cols, max_angles, truncated))
    # the continued row's total variation ripples with a period of about a pixel (the image grid against the
    # smeared edges): one parabola through every candidate, not the least's three; the window is centred on
    # its least again (twice at most), a parabola fitted off-centre to a curve as steep as this lying short of it
    c = start
    for _ in range(3):
        cand = np.arange(c - width, c + width + step / 2, step)
        a, b, _ = np.polyfit(cand - c, _total_variations(sinogram, theta_deg, cand, max_cols, max_angles, True), 2)
        if not a > 0:
            return c
        least = c - b / (2 * a)
        if abs(least - start) >= width:  # falls all the way to the window's edge
            return float(start + np.sign(least - start) * width)
        if abs(least - c) <= step:
            return float(least)
        c = float(least)
    return c


def center_sharpest(sinogram, theta_deg, *, search=(0.25, 0.75), max_cols=128, max_angles=256, truncated=False):
    """The axis column over the whole search whose filtered back-projection has the least total variation.

    :func:`center_sharpness`'s criterion, searched over the middle of the
    detector instead of about a start: the row binned to at most
    ``max_cols`` columns, candidates one binned column apart, the least
    refined by a parabola. Needs no air at the sides with ``truncated``
    and, unlike the seam of a 180-degree scan (:func:`center_seam`), no
    continuity between the scan's first and last projections, where the
    outer foam of a sample wider than the detector moves several pixels
    from one projection to the next: on the raw scans of ``python -m
    bubsub.bench fov --local-axis``, seeds 0-59, within 0.35 raw pixels of
    the axis on every seed, where the seam is 43 and 61 pixels off on two
    and the mean projection's symmetry (:func:`center_symmetry`) up to 37
    on others. ``margin`` says how distinct the least is: the next lowest
    local minimum more than three candidates away stands that fraction of
    the least above it (0.010-0.036 on those scans); a small margin means
    two columns sharpen the slice about as well.

    Parameters
    ----------
    sinogram : (n_angles, cols) float
        Line integrals of one detector row (phase-retrieved where phase
        contrast is strong).
    theta_deg : (n_angles,) float
        The angles, degrees.
    search : (float, float)
        Fractions of the detector width searched.
    max_cols, max_angles : int
        The row is binned to at most ``max_cols`` columns and at most
        ``max_angles`` projections are back-projected.
    truncated : bool
        The sample is wider than the detector (see :func:`center_sharpness`).

    Returns
    -------
    column : float
        Axis column (pixel index units of ``sinogram``).
    margin : float
        The next distinct local minimum's total variation over the least's, less one; ``inf`` where there is
        none, 0 where the least lies at the search's edge (no interior least).
    """
    cols = np.asarray(sinogram).shape[-1]
    step = float(-(-cols // max_cols))
    cand = np.arange(search[0] * (cols - 1), search[1] * (cols - 1) + 1e-9, step)
    cost = _total_variations(sinogram, theta_deg, cand, max_cols, max_angles, truncated)
    j = int(np.argmin(cost))
    if j in (0, cand.size - 1):
        return float(cand[j]), 0.0
    minima = [i for i in range(1, cand.size - 1) if cost[i] <= min(cost[i - 1], cost[i + 1]) and abs(i - j) > 3]
    margin = min(cost[i] for i in minima) / cost[j] - 1.0 if minima else np.inf
    return _least(cand, cost), float(margin)


def _total_variations(sinogram, theta_deg, candidates, max_cols, max_angles, truncated):
    """Total variation of the row's FBP over the central disc for each candidate axis column (see
    :func:`center_sharpness`)."""
    sino = np.asarray(sinogram, dtype=np.float32)
    if sino.ndim != 2 or sino.shape[0] < 4 or len(theta_deg) != sino.shape[0]:
        raise ValueError(f"the centre search needs a (n_angles >= 4, cols) sinogram and its angles, got shape "
                         f"{sino.shape} and {len(theta_deg)} angles")
    every = -(-sino.shape[0] // max_angles)
    sino, theta = sino[::every], np.radians(np.asarray(theta_deg, dtype=float)[::every])
    k = -(-sino.shape[1] // max_cols)
    cols = sino.shape[1] // k
    sino = sino[:, :cols * k].reshape(sino.shape[0], cols, k).mean(axis=2)
    pad = cols // 2 if truncated else 0
    if pad:
        sino = np.pad(sino, ((0, 0), (pad, pad)), mode="edge")
        cols += 2 * pad
    half = 0.5 * cols
    yy, xx = np.mgrid[:cols, :cols] + 0.5 - half
    disc = np.hypot(xx, yy) <= 0.8 * half
    cost = np.empty(len(candidates))
    base = ScanGeometry.parallel(theta, pixel_size=1.0, cols=cols).vectors
    with warnings.catch_warnings():
        # a short scan's FBP lacks Parker weights alike for every candidate: the comparison stands
        warnings.filterwarnings("ignore", message="FDK/FBP of a short or limited-angle scan")
        for i, c in enumerate(candidates):
            v = np.array(base)
            v[:, 2:4] += (cols / 2 - 0.5 - ((c + 0.5) / k - 0.5 + pad)) * v[:, 4:6]  # the axis at column c of the row
            image = reconstruct_2d("fbp", sino, ScanGeometry.from_astra("parallel_vec", v, det_count=cols),
                                   (cols, cols), (-half, half, -half, half))
            gy, gx = np.gradient(image)
            cost[i] = float(np.hypot(gx, gy)[disc].sum())
    return cost


def _least(candidates, cost):
    """The evenly spaced candidate of least cost, refined by a parabola through it and its neighbours."""
    j = int(np.argmin(cost))
    c = float(candidates[j])
    if 0 < j < len(candidates) - 1:
        den = cost[j - 1] - 2 * cost[j] + cost[j + 1]
        if den > 0:
            c += 0.5 * (cost[j - 1] - cost[j + 1]) / den * (candidates[1] - candidates[0])
    return c
