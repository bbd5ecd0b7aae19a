"""Single-distance phase retrieval (Paganin et al. 2002), TomoPy-compatible.

For a single material with refractive index ``n = 1 - delta + i beta``,
imaged at a propagation distance ``z`` with wavelength ``lambda``, the
intensity transmission ``T = I / I0`` is filtered in Fourier space by::

    H(u) = 1 / (1 + pi * lambda * z * (delta / beta) * |u|^2)

(``u`` in cycles per mm), and ``-log`` of the filtered transmission is the
attenuation line integral ``mu * t`` of the projected thickness ``t``
(``mu = 4 pi beta / lambda``). TomoPy's ``retrieve_phase(alpha=)`` is the
same filter with ``alpha = beta / delta`` (it writes
``alpha / (lambda z w^2 / (4 pi) + alpha)`` with the angular frequency
``w = 2 pi u``); here the ratio ``delta / beta`` is given, as the paper does.
The image is padded (edge values, to at least twice its size rounded up to
a fast FFT length) so that the filter does not wrap around.
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft

__all__ = ["wavelength_mm", "paganin_transfer", "paganin_filter", "fresnel_propagate", "HC_KEV_MM"]

#: h c in keV mm: lambda (mm) = HC_KEV_MM / E (keV).
HC_KEV_MM = 12.398419843320026e-7


def wavelength_mm(energy_kev):
    """X-ray wavelength in mm for a photon energy in keV."""
    e = float(energy_kev)
    if not np.isfinite(e) or e <= 0:
        raise ValueError(f"energy must be a positive number of keV, got {energy_kev!r}")
    return HC_KEV_MM / e


def paganin_transfer(freq_sq, *, energy, distance, delta_beta):
    """The Paganin filter ``H = 1 / (1 + pi lambda z (delta/beta) u^2)``.

    Parameters
    ----------
    freq_sq : ndarray
        ``|u|^2`` in (cycles/mm)^2.
    energy : float
        keV.
    distance : float
        Sample-detector distance, mm.
    delta_beta : float
        ``delta / beta`` of the material (> 0).
    """
    lam = wavelength_mm(energy)
    return 1.0 / (1.0 + np.pi * lam * float(distance) * float(delta_beta) * np.asarray(freq_sq))


def _check(pixel_size, distance, delta_beta):
    for name, v in (("pixel_size", pixel_size), ("distance", distance), ("delta_beta", delta_beta)):
        if not np.isfinite(v) or v <= 0:
            raise ValueError(f"Paganin phase retrieval needs a positive {name}, got {v!r}")


def _freq_sq(shape, pixel_size):
    ky = sfft.fftfreq(shape[0], d=pixel_size[0])
    kx = sfft.rfftfreq(shape[1], d=pixel_size[1])
    return ky[:, None] ** 2 + kx[None, :] ** 2


def paganin_filter(transmission, *, pixel_size, energy, distance, delta_beta, pad=True):
    """Apply the Paganin filter to intensity transmissions.

    Parameters
    ----------
    transmission : (rows, cols) or (n, rows, cols) float
        Flat-field-corrected intensity ``I / I0``.
    pixel_size : float or (2,) float
        Detector pixel size (row height, column width), mm.
    energy : float
        keV.
    distance : float
        Sample-detector distance, mm.
    delta_beta : float
        ``delta / beta`` of the single material.
    pad : bool
        Pad with edge values to a fast FFT size of at least twice the image.

    Returns
    -------
    ndarray float32, same shape
        The filtered transmission; ``-log`` of it is ``mu * t``.
    """
    a = np.asarray(transmission, dtype=np.float32)
    if a.ndim not in (2, 3):
        raise ValueError(f"transmission must be (rows, cols) or (n, rows, cols), got shape {a.shape}")
    px = np.broadcast_to(np.asarray(pixel_size, dtype=float), (2,))
    _check(float(px.min()), float(distance), float(delta_beta))
    stack = a[None] if a.ndim == 2 else a
    rows, cols = stack.shape[1:]
    if pad:
        pr, pc = sfft.next_fast_len(2 * rows, real=True), sfft.next_fast_len(2 * cols, real=True)
    else:
        pr, pc = rows, cols
    h = paganin_transfer(_freq_sq((pr, pc), px), energy=energy, distance=distance, delta_beta=delta_beta)
    r0, c0 = (pr - rows) // 2, (pc - cols) // 2
    out = np.empty_like(stack)
    for i, img in enumerate(stack):
        padded = np.pad(img, ((r0, pr - rows - r0), (c0, pc - cols - c0)), mode="edge") if pad else img
        f = sfft.rfft2(padded, workers=-1)
        f *= h
        out[i] = sfft.irfft2(f, s=(pr, pc), workers=-1)[r0:r0 + rows, c0:c0 + cols]
    return out[0] if a.ndim == 2 else out


def fresnel_propagate(field, *, pixel_size, energy, distance):
    """Fresnel (paraxial) free-space propagation of a complex wave field.

    Multiplies the field's spectrum by ``exp(-i pi lambda z |u|^2)``
    (periodic boundaries: pad the field yourself if it matters).

    Parameters
    ----------
    field : (cols,) or (rows, cols) complex
        Exit wave after the sample (``exp(-k (beta + i delta) t)`` for a
        thickness ``t``, ``k = 2 pi / lambda``).
    pixel_size : float
        Sampling of the field, mm.
    energy : float
        keV.
    distance : float
        mm.

    Returns
    -------
    ndarray complex128, same shape
        The field at the detector; ``abs(.)**2`` is the intensity.
    """
    f = np.asarray(field, dtype=np.complex128)
    lam = wavelength_mm(energy)
    if f.ndim == 1:
        u2 = sfft.fftfreq(f.shape[0], d=pixel_size) ** 2
    elif f.ndim == 2:
        u2 = sfft.fftfreq(f.shape[0], d=pixel_size)[:, None] ** 2 + sfft.fftfreq(f.shape[1], d=pixel_size)[None] ** 2
    else:
        raise ValueError(f"field must be 1D or 2D, got shape {f.shape}")
    kernel = np.exp(-1j * np.pi * lam * float(distance) * u2)
    axes = tuple(range(f.ndim))
    return sfft.ifftn(sfft.fftn(f, axes=axes, workers=-1) * kernel, axes=axes, workers=-1)
