"""Filtered backprojection in numpy: FDK for circular cone scans, FBP for parallel beams.

Feldkamp-Davis-Kress for circular cone scans about the z axis (and plain
FBP for parallel beams): cosine pre-weighting ``D_sd / |pixel - source|``,
a ramp filter along detector rows (Ram-Lak, Shepp-Logan, cosine, Hamming or
Hann window, zero padded), and voxel-driven backprojection with bilinear
interpolation and weight ``R D_sd / depth^2``, where ``R`` is the source's
distance from the axis, ``D_sd`` the source-detector distance and ``depth``
the voxel's distance from the source along the detector normal. Projection
angles need not be uniform: each projection is weighted by its angular
interval. Short scans (no Parker weights) are only approximate.

2D scans are embedded in 3D as :mod:`.projector3d` does.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from bubsub.core.voxel.projector3d import VoxelProjector

__all__ = ["fdk", "ramp_filter", "FILTERS"]

#: Names accepted by the ``filter`` argument of :func:`fdk` and ``reconstruct_*``.
FILTERS = ("ram-lak", "shepp-logan", "cosine", "hamming", "hann")

_F32 = np.float32


# -- FDK ----------------------------------------------------------------------------
def ramp_filter(n, spacing, filter="ram-lak"):
    """Frequency response of the discrete ramp filter for rows of ``n`` samples.

    Uses the band-limited spatial kernel of Kak & Slaney (``h[0] = 1/(4 tau^2)``,
    ``h[k odd] = -1/(pi k tau)^2``), zero padded to avoid wrap-around, times
    ``tau`` (the integral's sample spacing) and a window.

    Parameters
    ----------
    n : int
        Samples per row.
    spacing : float
        Sample spacing ``tau`` (mm).
    filter : str
        One of :data:`FILTERS`.

    Returns
    -------
    H : (npad // 2 + 1,) float64
        For ``numpy.fft.rfft`` of rows zero padded to ``npad``.
    npad : int
    """
    if filter not in FILTERS:
        raise ValueError(f"unknown filter {filter!r}; expected one of {FILTERS}")
    npad = max(64, 1 << int(math.ceil(math.log2(2 * n))))
    k = np.arange(npad)
    k = np.where(k > npad // 2, k - npad, k)
    h = np.zeros(npad)
    h[0] = 1.0 / (4.0 * spacing**2)
    odd = (k % 2) == 1
    h[odd] = -1.0 / (np.pi * k[odd] * spacing) ** 2
    H = np.real(np.fft.rfft(h)) * spacing
    f = np.fft.rfftfreq(npad)  # cycles per sample, 0 .. 0.5
    if filter == "shepp-logan":
        H *= np.sinc(f)
    elif filter == "cosine":
        H *= np.cos(np.pi * f)
    elif filter == "hamming":
        H *= 0.54 + 0.46 * np.cos(2 * np.pi * f)
    elif filter == "hann":
        H *= 0.5 + 0.5 * np.cos(2 * np.pi * f)
    return H, npad


def _angular_weights(angles, period):
    """Angular interval of each projection, rescaled by pi / coverage.

    Projections at the same angle share an interval. Gaps much larger than
    the mean spacing (short or limited-angle scans) count as one typical step.
    """
    n = angles.size
    a = np.mod(angles, period)
    order = np.argsort(a, kind="stable")
    s = a[order]
    gaps = np.diff(np.concatenate([s, [s[0] + period]]))  # gap after each sorted angle
    big = gaps > 2.5 * period / n
    short = bool(np.any(big))
    if short:
        typical = np.median(gaps[~big]) if np.any(~big) else period / n
        gaps = np.where(big, typical, gaps)
    before = np.roll(gaps, 1)
    w_sorted = 0.5 * (gaps + before)
    w = np.empty(n)
    w[order] = w_sorted
    coverage = w.sum()
    return w * (np.pi / coverage), short


def _fdk_prepare(geom3, p, filter):
    """Cosine-weight and ramp-filter the projections (n, rows, cols) -> float32, and per-angle weights."""
    vec = geom3.vectors
    n, rows, cols = p.shape
    src, D, U, V = vec[:, 0:3], vec[:, 3:6], vec[:, 6:9], vec[:, 9:12]
    N = np.cross(U, V)
    nhat = N / np.linalg.norm(N, axis=1, keepdims=True)
    if geom3.is_cone:
        sgn = np.sign(np.sum((D - src) * nhat, axis=1))
        nhat = nhat * sgn[:, None]
        angles = np.arctan2(src[:, 1], src[:, 0])
        period = 2 * np.pi
        spacing = np.linalg.norm(U, axis=1)
    else:
        r = src / np.linalg.norm(src, axis=1, keepdims=True)
        angles = np.arctan2(r[:, 1], r[:, 0])
        period = np.pi
        u_perp = U - np.sum(U * r, axis=1)[:, None] * r
        spacing = np.linalg.norm(u_perp, axis=1)
    dtheta, short = _angular_weights(angles, period)
    if short:
        warnings.warn(
            "FDK/FBP of a short or limited-angle scan: no Parker weights, the result is approximate",
            stacklevel=3,
        )
    out = np.empty((n, rows, cols), dtype=_F32)
    cc = np.arange(cols) - cols / 2 + 0.5
    rr = np.arange(rows) - rows / 2 + 0.5
    for i in range(n):
        q = p[i].astype(np.float64)
        if geom3.is_cone:
            pix = D[i] + cc[None, :, None] * U[i] + rr[:, None, None] * V[i]
            dsd = float(np.dot(D[i] - src[i], nhat[i]))
            q = q * (dsd / np.linalg.norm(pix - src[i], axis=-1))
        H, npad = ramp_filter(cols, spacing[i], filter)
        q = np.fft.irfft(np.fft.rfft(q, n=npad, axis=-1) * H, n=npad, axis=-1)[:, :cols]
        out[i] = q
    return out, dtheta


def fdk(
    projections,
    geometry,
    shape,
    extent=None,
    *,
    pixel_size=None,
    centre=None,
    filter="ram-lak",
    threads=None,
    slab_voxels=1 << 17,
):
    """FDK (cone beam) or FBP (parallel beam) reconstruction, numpy only.

    Parameters
    ----------
    projections : ndarray
        ``(angle, row, col)`` for 3D geometries, ``(angle, col)`` for 2D ones.
    geometry : ScanGeometry or ASTRA proj_geom dict
        ``cone_vec`` / ``fanflat_vec``: a circular orbit about the z axis
        (full 360 degrees for exact weights); ``parallel3d_vec`` /
        ``parallel_vec``: rays perpendicular to z (180 or 360 degrees).
    shape : (slices, rows, cols) or (rows, cols)
    extent, pixel_size, centre
        The grid (see :func:`bubsub.core.voxel.grid.resolve_grid`).
    filter : str
        One of :data:`FILTERS`.
    threads : int, optional
    slab_voxels : int

    Returns
    -------
    ndarray float32, shape ``shape``
        Attenuation, 1/mm.
    """
    proj = VoxelProjector(
        geometry, shape, extent, pixel_size=pixel_size, centre=centre, detector_binning=None,
        threads=threads, slab_voxels=slab_voxels,
    )
    p = np.asarray(projections)
    if p.shape != tuple(proj.proj_shape):
        raise ValueError(f"projections must have shape {tuple(proj.proj_shape)}, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("projections contain NaN or inf")
    if proj._is_2d:
        p = p[:, None, :]
    q, dtheta = _fdk_prepare(proj._geom3, p, filter)
    q *= dtheta.astype(_F32)[:, None, None]
    return proj._backproject(q, "fdk", skip=dtheta == 0)
