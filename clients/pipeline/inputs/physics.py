"""Data no foam can give, refused before any work: the bubble signal's sign and size against the liquid and
the contrast (:func:`check_physical_signal`)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from bubsub.clients.pipeline.inputs.fov import FOV_EXTEND
from bubsub.clients.pipeline.inputs.sides import LOCAL_VIEWS, side_hits
from bubsub.core.prep.background import noise_level

__all__ = ["check_physical_signal", "longest_path", "liquid_attenuation", "away_from", "IMPOSSIBLE_FRACTION",
           "CONTRAST_MARGIN", "AIR_MARGIN", "AIR_FRACTION"]


#: Most fraction of the values that may pass a bound of :func:`check_physical_signal` by more than the noise
#: before the scan is refused: a few defective detector columns (each 1/cols of the values) stay below it, a
#: signal beyond the physics shows in far more (a foam's data with their sign flipped: all of them).
IMPOSSIBLE_FRACTION = 0.002



def longest_path(geometry):
    """The longest path (mm) a ray of ``geometry`` can take through the region the pipeline models.

    That region is the cylinder of :data:`bubsub.clients.pipeline.inputs.fov.FOV_EXTEND` times the detector's half-width in the object
    plane (the largest over the projections; for a centred detector the preview's region,
    :data:`bubsub.clients.pipeline.inputs.fov.FOV_EXTEND` times the field of view's radius): a ray crosses it over
    at most its diameter divided by the cosine of the ray's tilt out of the x-y plane (0 in 2D and for a
    parallel beam perpendicular to the axis; largest at the middle of a cone beam's top and bottom rows).

    Parameters
    ----------
    geometry : bubsub.core.ScanGeometry

    Returns
    -------
    float
        mm.
    """
    n = geometry.ndim
    vec = geometry.vectors
    s, d, u = vec[:, :n], vec[:, n:2 * n], vec[:, 2 * n:3 * n]
    half_w = 0.5 * geometry.det_cols * np.linalg.norm(u, axis=1)
    if geometry.is_cone:  # the detector's width shrunk by the magnification onto the rotation axis
        half_w = half_w * np.linalg.norm(s, axis=1) / np.linalg.norm(s - d, axis=1)
    diameter = 2.0 * FOV_EXTEND * float(np.max(half_w))
    if geometry.ndim == 2:
        return diameter
    views = geometry[::max(1, geometry.n_angles // 32)]
    flat = 1.0
    for row in (0, geometry.det_rows - 1):  # the steepest rays: a cone's top and bottom rows
        _, d = views.window(row, 0, rows=1, cols=geometry.det_cols).rays()
        flat = min(flat, float(np.min(np.hypot(d[..., 0], d[..., 1]))))
    return diameter / max(flat, 1e-6)


def check_physical_signal(scan):
    """Refuse data no foam can give: the bubble signal's sign and size against the liquid and the contrast.

    Along each ray the line integral is ``data = background + c L``, with
    ``c`` the bubble contrast (gas minus liquid attenuation, 1/mm) and ``L``
    the length (mm) of the ray's path through gas. Whatever the sample,
    within the noise:

    1. the projections vary: one value everywhere is no image of a sample;
    2. with ``/exchange/background``, ``background >= 0`` and ``data >= 0``:
       nothing in the beam attenuates negatively, so a bubble removes at most
       the liquid on its ray (the gas attenuation, liquid plus ``c``, is
       ``>= 0`` and ``L`` is at most the liquid's path) and the bubble signal
       ``data - background`` never falls below ``-background``;
    3. ``L = (data - background) / c`` is at most the longest path through the
       modelled region (:func:`longest_path`): a contrast far too small in
       magnitude (or in the wrong unit), or data scaled by a factor, imply
       gas paths longer than the sample;
    4. with a background, ``|c|`` is at most the liquid's attenuation (the
       gas's, liquid plus ``c``, is ``>= 0``), read from the background as
       its largest value over the liquid's widest shadow
       (:func:`liquid_attenuation`), within :data:`CONTRAST_MARGIN`: a
       contrast in 1/m instead of 1/mm is refused;
    5. with a background, the rays that miss the liquid (:data:`AIR_MARGIN`
       columns or more from its shadow) cross nothing that attenuates and no
       bubble: their data are 0 (refused when more than
       :data:`AIR_FRACTION` of them are not: transmissions written as line
       integrals, say).

    :func:`check_bubble_signal` checks the signal's sign (most of its mass
    on the contrast's side) before this; this check bounds each value. The
    noise ``sigma`` is :func:`bubsub.core.prep.background.noise_level` of
    ``data`` (differences of adjacent columns); a value breaks a bound when
    it passes it by more than ``max(6 sigma, 5 % of the 99th percentile of
    |data|)`` (the 5 %: room for a flat field's drift, which offsets whole
    projections, and phase-retrieval fringes at edges), and the scan is refused when more than
    :data:`IMPOSSIBLE_FRACTION` of the values do. NaN, inf and a zero
    contrast are refused when the file is read
    (:func:`bubsub.core.io.scanfile.read_scan`).

    Parameters
    ----------
    scan : bubsub.core.io.scanfile.Scan
        ``data`` and ``background`` ``(views, cols)`` or ``(views, rows, cols)``.

    Raises
    ------
    ValueError
        One line naming the bound broken, by how many values and how far, and what to correct.
    """
    name = scan.path.name if scan.path is not None else "the scan"
    data, bg, c = scan.data, scan.background, scan.bubble_contrast
    # the noise and the scale from some views (and rows): the same level, a fraction of a second on any scan
    some = data[::max(1, data.shape[0] // 64)]
    if some.ndim == 3:
        some = some[:, ::max(1, -(-some.size // 1_000_000))]
    sigma = noise_level(some)
    tol = max(6.0 * sigma, 0.05 * float(np.percentile(np.abs(some), 99)))
    lo, hi = float(data.min()), float(data.max())
    if hi - lo <= tol:
        spread = f"are all {lo:.4g}" if hi == lo else f"vary only from {lo:.4g} to {hi:.4g}, within the noise"
        raise ValueError(
            f"{name}: the values of /exchange/data {spread}: the projections hold no image of a sample; write "
            f"the scan's line integrals, -log(transmission), to it")
    prepare = "make it with `bubsub prepare --background auto`"
    if bg is not None:
        n_bg = int(np.count_nonzero(bg < -tol))
        if n_bg > IMPOSSIBLE_FRACTION * bg.size:
            raise ValueError(
                f"{name}: {100 * n_bg / bg.size:.3g} % of /exchange/background is negative (down to "
                f"{float(bg.min()):.4g}, beyond the tolerance {tol:.2g}): the liquid's projection cannot attenuate "
                f"negatively; {prepare}")
        n_neg = int(np.count_nonzero(data < -tol))
        if n_neg > IMPOSSIBLE_FRACTION * data.size:
            raise ValueError(
                f"{name}: {100 * n_neg / data.size:.3g} % of the line integrals in /exchange/data are negative "
                f"(down to {lo:.4g}, beyond the tolerance {tol:.2g}), so the bubble signal data - background exceeds "
                f"the whole liquid's projection there, more than a bubble filling all the liquid on a ray could "
                f"remove; /exchange/data must hold -log(transmission) of the sample with its liquid and "
                f"/exchange/background the liquid's projection alone ({prepare})")
        air = away_from(bg > tol, AIR_MARGIN)
        n_air = int(np.count_nonzero(air))
        lit = air & (np.abs(data) > tol)
        n_lit = int(np.count_nonzero(lit))
        if n_lit > AIR_FRACTION * n_air:
            raise ValueError(
                f"{name}: on {100 * n_lit / n_air:.3g} % of the rays that miss the liquid (/exchange/background "
                f"0, {AIR_MARGIN} columns or more from it) /exchange/data is not 0 (up to "
                f"{float(np.abs(data[lit]).max()):.4g}, beyond the tolerance {tol:.2g}): nothing attenuates there "
                f"and bubbles lie in the liquid; /exchange/data must hold -log(transmission), 0 in air (check the "
                f"flat-field correction), and /exchange/background the liquid's projection ({prepare})")
        mu, width, top = liquid_attenuation(bg, scan.geometry, tol)
        if mu > 0 and abs(c) > CONTRAST_MARGIN * mu:
            raise ValueError(
                f"{name}: bubble_contrast = {c:g} 1/mm is larger in magnitude than the liquid's attenuation can "
                f"be: its projection (/exchange/background) reaches {top:.4g} across a liquid {width:.4g} mm wide, "
                f"about {mu:.3g} 1/mm, and gas minus liquid cannot exceed the liquid's own; correct "
                f"bubble_contrast (gas minus liquid attenuation in 1/mm, not 1/m or 1/cm)")
    longest = longest_path(scan.geometry)
    gas = np.sign(c) * scan.bubble_data  # c L: positive along gas
    n_long = int(np.count_nonzero(gas > abs(c) * longest + tol))
    if n_long > IMPOSSIBLE_FRACTION * gas.size:
        hit_l, hit_r, n = side_hits(scan)
        if max(hit_l, hit_r) >= LOCAL_VIEWS * n:
            # a foam wider than the detector: its gas paths run beyond the modelled region, by how much the
            # scan does not say, so the bound is no proof of a wrong contrast here
            return
        raise ValueError(
            f"{name}: with bubble_contrast = {c:g} 1/mm the bubble signal implies gas paths up to "
            f"{float(gas.max()) / abs(c):.4g} mm on {100 * n_long / gas.size:.3g} % of the rays, longer than the "
            f"{longest:.4g} mm any ray crosses of the field of view: bubble_contrast (gas minus liquid "
            f"attenuation, 1/mm) is too small in magnitude for these data, or the data are scaled; correct it")


#: How many times the liquid's attenuation (:func:`liquid_attenuation`) the bubble contrast's magnitude may be
#: before :func:`check_physical_signal` refuses it: at most 1 in physics (the gas attenuates at least nothing);
#: the margin covers a liquid whose longest path is shorter than its width (not convex) and a container's
#: wall in the background. A contrast in 1/m instead of 1/mm is 1000 times too large.
CONTRAST_MARGIN = 4.0


def liquid_attenuation(background, geometry, tol=0.0):
    """The liquid's attenuation as its projection shows it: the background's largest value over the
    liquid's largest width.

    For a convex liquid the longest path a ray takes through it is its widest shadow on the detector (its
    diameter, for a scan around it), so ``max(background) / width`` is its attenuation (a container's wall
    in the background makes it larger).

    Parameters
    ----------
    background : ndarray, ``(views, cols)`` or ``(views, rows, cols)``
        The liquid's projection, line integrals.
    geometry : bubsub.core.ScanGeometry
        Of ``background``.
    tol : float
        Values up to this count as air.

    Returns
    -------
    mu : float
        1/mm; 0 when the background holds no liquid.
    width : float
        mm, in the object plane (a cone beam's columns shrunk by the magnification).
    top : float
        The background's largest value.
    """
    b = np.asarray(background).reshape(background.shape[0], -1, background.shape[-1])
    wet = b > tol
    seen = wet.any(axis=-1)
    if not seen.any():
        return 0.0, 0.0, 0.0
    first = np.argmax(wet, axis=-1)
    last = wet.shape[-1] - 1 - np.argmax(wet[..., ::-1], axis=-1)
    n = geometry.ndim
    vec = geometry.vectors
    pitch = np.linalg.norm(vec[:, 2 * n:3 * n], axis=1)
    if geometry.is_cone:
        pitch = pitch * np.linalg.norm(vec[:, :n], axis=1) / np.linalg.norm(vec[:, :n] - vec[:, n:2 * n], axis=1)
    widths = np.where(seen, (last - first + 1) * pitch[:, None], 0.0)
    width, top = float(widths.max()), float(b.max())
    return top / width, width, top


#: Columns a ray must lie from the liquid's shadow for :func:`check_physical_signal` to count it as missing the
#: liquid (its edge blurs by a pixel or two, more with phase retrieval), and the most fraction of those rays whose
#: data may stand beyond the tolerance (a sample in transmission instead of line integrals: all of them).
AIR_MARGIN = 4
AIR_FRACTION = 0.05


def away_from(mask, margin):
    """Where ``mask`` is False and stays so for ``margin`` columns either way (along the last axis).

    Parameters
    ----------
    mask : bool ndarray, ``(..., cols)``
    margin : int

    Returns
    -------
    bool ndarray, ``mask.shape``
    """
    size = [1] * mask.ndim
    size[-1] = 2 * margin + 1
    return ~ndimage.maximum_filter(mask, size=size, mode="nearest")
