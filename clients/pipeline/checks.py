"""Checks run before a reconstruction computes anything: settings and the scan's bubble signal.

Each takes well under a second and raises ``ValueError`` with one line that
names the problem and the fix, so that a mistake costs seconds, not a fit,
and never yields a silent wrong result.
"""

from __future__ import annotations

import logging
import weakref

import numpy as np

from bubsub.core.contrast import signal_masses
from bubsub.core.validate import check_int

__all__ = ["check_settings", "check_bubble_signal", "check_lateral_truncation", "side_signal", "CONTROL_POINTS_3D",
           "MAX_LEVELS", "TRUNCATED_VIEWS", "LOCAL_VIEWS", "side_bubble_signal", "side_hits", "check_physical_signal",
           "longest_path", "IMPOSSIBLE_FRACTION", "liquid_attenuation", "CONTRAST_MARGIN",
           "away_from", "AIR_MARGIN", "AIR_FRACTION"]

#: Control vertices of the icosphere control meshes (3D bubbles).
CONTROL_POINTS_3D = (12, 42, 162)
#: Subdivision levels beyond this cost far more than they add (4**levels faces per control face).
MAX_LEVELS = 4


def check_settings(settings, ndim):
    """Refuse reconstruction settings that cannot work for a ``ndim``-D scan.

    Parameters
    ----------
    settings : ReconstructionSettings
    ndim : {2, 3}

    Raises
    ------
    ValueError
        Naming the setting (as its command-line option) and the allowed values.
    """
    s = settings
    check_int(s.iterations, "--iterations", 0)
    check_int(s.levels, "--levels", 0)
    if s.levels > MAX_LEVELS:
        raise ValueError(f"--levels must be at most {MAX_LEVELS} (each level multiplies the faces by 4), "
                         f"got {s.levels}")
    if isinstance(s.facet_pixels, bool) or not isinstance(s.facet_pixels, (int, float)) \
            or not (np.isfinite(s.facet_pixels) and s.facet_pixels >= 0):
        raise ValueError(f"--facet-pixels must be a number of pixels >= 0 (0: every bubble at --levels), "
                         f"got {s.facet_pixels!r}")
    check_int(s.supersampling, "--supersampling", 1)
    if s.control_points is not None:
        if ndim == 3 and s.control_points not in CONTROL_POINTS_3D:
            raise ValueError(f"--control-points must be one of {list(CONTROL_POINTS_3D)} for a 3D scan "
                             f"(icosphere control meshes), got {s.control_points}")
        check_int(s.control_points, "--control-points", 3)
    for name in ("radius", "voxel_size", "min_distance"):
        v = getattr(s, name)
        if v is not None and not (np.isfinite(v) and v > 0):
            raise ValueError(f"{name.replace('_', '-')} must be a positive number of mm, got {v!r}")
    if s.detector not in (None, "auto", "log", "dt"):
        raise ValueError(f"--detector must be 'auto', 'log' or 'dt', got {s.detector!r}")
    if not (np.isfinite(s.separation) and s.separation >= 0):
        raise ValueError(f"--separation must be a non-negative number, got {s.separation!r}")
    if s.holdout not in (None, "odd", "even"):
        raise ValueError(f"--holdout must be 'odd' or 'even', got {s.holdout!r}")
    if s.data_levels is not None:
        check_int(s.data_levels, "--data-levels", 1)
    if s.fit_rtol is not None and not (np.isfinite(s.fit_rtol) and 0 <= s.fit_rtol < 1):
        raise ValueError(f"--fit-rtol must be a number in [0, 1), got {s.fit_rtol!r}")


def check_bubble_signal(scan, *, background_subtracted=False, sides=True):
    """Refuse a scan whose bubble data disagree with the sign of ``bubble_contrast``.

    Gas bubbles lower the attenuation, so ``data - background`` of a foam is
    negative where a bubble is and noise elsewhere, and ``bubble_contrast``
    (gas minus liquid) is negative. Two mistakes give a meaningless fit:
    a scan without ``/exchange/background`` (``data`` then holds the whole
    liquid's projection, positive) and a contrast of the wrong sign.

    Parameters
    ----------
    scan : bubsub.core.io.scanfile.Scan
    background_subtracted : bool
        The user states that ``data`` already holds only the bubbles'
        projection; accepts a positive contrast without a background.
    sides : bool
        Also say whether the bubbles reach the detector's sides (:func:`check_lateral_truncation`); False for
        a probe of some rows ahead of a reconstruction that checks its scan again.

    Raises
    ------
    ValueError
        If ``sign(bubble_contrast) * (data - background)`` has more mass
        below zero than above (the sign disagrees with the data, or the
        liquid was not subtracted), if it is zero everywhere, or if the
        contrast is positive and the scan has no background (unless
        ``background_subtracted``).
    """
    c = scan.bubble_contrast
    name = scan.path.name if scan.path is not None else "the scan"
    has_bg = scan.background is not None
    above, below = signal_masses(np.sign(c) * scan.bubble_data)
    prepare = "subtract the liquid's projection with `bubsub prepare --background auto`"
    if above == 0 and below == 0:
        raise ValueError(f"{name}: data - background is zero everywhere: there is no bubble signal to fit")
    if below > above:
        if not has_bg:
            raise ValueError(
                f"{name} has no /exchange/background and its projections are mostly "
                f"{'positive' if c < 0 else 'negative'}, the opposite sign of bubble_contrast = {c:g} 1/mm: "
                f"they hold the liquid's projection, not the bubbles'; {prepare}, or correct bubble_contrast")
        raise ValueError(
            f"{name}: bubble_contrast = {c:g} 1/mm disagrees with the data: data - background is mostly "
            f"{'positive' if c < 0 else 'negative'} (gas bubbles lower the attenuation, so it should be "
            f"negative with a negative contrast); check the sign of bubble_contrast and the background")
    if c > 0 and not has_bg and not background_subtracted:
        raise ValueError(
            f"{name} has a positive bubble_contrast = {c:g} 1/mm (bubbles attenuating more than the liquid) "
            f"and no /exchange/background, so the fit would take the liquid for bubbles; gas bubbles have a "
            f"negative contrast: correct its sign and {prepare}; if the data really hold only the bubbles' "
            f"projection, pass --background-subtracted")
    check_physical_signal(scan)
    if sides:
        check_lateral_truncation(scan)


#: Least fraction of the projections in which the bubbles' signal reaches a side of the detector for
#: :func:`check_lateral_truncation` to warn (a few bubbles partly outside the field of view, which the model covers).
TRUNCATED_VIEWS = 0.1
#: Least fraction for it to call the scan local tomography (a foam wider than the detector reaches both sides in
#: every projection).
LOCAL_VIEWS = 0.5
#: Fraction of the bubbles' signal's 99th percentile above which a side counts as reached: well above the residue
#: of flat-field and background errors, well below a foam's signal along the rays that graze the field of view.
SIDE_FRACTION = 0.15

#: Columns at each side of the detector whose values :func:`side_signal` takes.
SIDE_COLUMNS = 2


def side_signal(values):
    """How far a projection array's outermost columns stand above the air level, view by view.

    Parameters
    ----------
    values : ndarray, ``(views, cols)`` or ``(views, rows, cols)``
        Line integrals of what attenuates (the sample, or the bubbles' signal made positive).

    Returns
    -------
    left, right : (views,) float
        Median over rows (and the :data:`SIDE_COLUMNS` outermost columns) of each side.
    level : float
        Above it a side sees the sample: 6 standard errors of that median in air (the noise estimated
        from neighbouring side columns' differences, robustly) or 1 % of the array's 99th percentile,
        whichever is larger.
    """
    a = np.asarray(values, dtype=np.float32)
    a = a.reshape(a.shape[0], -1, a.shape[-1])
    k = min(SIDE_COLUMNS, a.shape[-1] // 4)
    if k < 1:
        raise ValueError(f"a detector of {a.shape[-1]} columns is too narrow to check its sides")
    left, right = a[:, :, :k], a[:, :, -k:]
    # adjacent side columns differ by noise only (a smooth sample changes little over one pixel)
    d = np.diff(np.concatenate([a[:, :, :k + 1], a[:, :, -k - 1:]], axis=2), axis=2)
    sigma = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / np.sqrt(2)
    per_view = a.shape[1] * k
    # the percentile from every few rows: the same level, a fraction of a second less on a tall detector
    step = max(1, a.shape[1] // 64)
    level = max(6 * 1.25 * sigma / np.sqrt(per_view), 0.01 * float(np.percentile(a[:, ::step], 99)))
    return (np.median(left.reshape(len(a), -1), axis=1), np.median(right.reshape(len(a), -1), axis=1), level)


def check_lateral_truncation(scan):
    """Say when the bubbles reach the detector's sides: a foam wider than the detector, or a few bubbles.

    The pipeline models what the data see: bubbles within 1.25 times the
    radius of the cylinder every projection sees
    (:data:`bubsub.clients.pipeline.fov.FOV_EXTEND`) and, through
    ``/exchange/background``, everything else (the liquid, the container).
    What can harm is gas the model does not hold: the bubbles' signal
    ``sign(contrast) * (data - background)`` (:attr:`Scan.bubble_data`,
    positive along gas) at the detector's sides. A liquid wider than the
    detector, or its edge spread into the outermost columns by phase
    retrieval, is in the background and harmless, so the liquid itself is
    not judged. Per projection, each side's signal (:func:`side_signal`)
    is taken relative to a slow drift common to both sides (a quadratic
    over the projections: a flat-field normalisation that follows the
    beam's decay imperfectly offsets whole projections), and counts when
    it stands above :data:`SIDE_FRACTION` of the signal's 99th percentile
    (and the noise). In at least :data:`LOCAL_VIEWS` of the projections the
    foam is wider than the detector (local tomography); in at least
    :data:`TRUNCATED_VIEWS` some bubbles reach beyond the field of view.
    Either way one line is logged (logger ``bubsub``, once per scan) and the
    reconstruction goes on: the field-of-view model fits the bubbles out to
    1.25 times the field of view's radius, which is what keeps the gas
    beyond it from becoming spurious or swollen bubbles inside (measured on
    foams 1.5 times the field of view's radius: docs/prepare.md), bubbles
    cut by the cylinder's side are flagged ``truncated`` and measured by
    their part inside it, and ``bubsub analyse`` keeps its statistics to the
    interior.

    Parameters
    ----------
    scan : bubsub.core.io.scanfile.Scan

    Returns
    -------
    str or None
        The line logged, if any.
    """
    name = scan.path.name if scan.path is not None else "the scan"
    hit_l, hit_r, n = side_hits(scan)
    where = (f"the bubbles' signal (data - background) reaches the detector's left side in {hit_l} and its right "
             f"side in {hit_r} of {n} projections")
    if max(hit_l, hit_r) < TRUNCATED_VIEWS * n:
        return None
    if max(hit_l, hit_r) >= LOCAL_VIEWS * n:
        text = (f"note: {name} is local tomography (the foam is wider than the detector): {where}; the bubbles are "
                f"reconstructed within the field of view, those cut by its side flagged truncated, and bubsub "
                f"analyse keeps its statistics to the interior")
    else:
        text = (f"warning: {name}: {where}: bubbles partly outside the field of view are modelled, but check the "
                f"bubbles flagged truncated at the edge")
    if _WARNED.get(id(scan)) is not scan:  # once per scan (the command line checks before reconstruct does)
        _WARNED[id(scan)] = scan
        logging.getLogger("bubsub").warning(text)
    return text


#: Scans already warned about, by id (entries vanish with their scan).
_WARNED = weakref.WeakValueDictionary()


def side_hits(scan):
    """In how many projections the bubbles' signal reaches the detector's left and right sides.

    Parameters
    ----------
    scan : bubsub.core.io.scanfile.Scan

    Returns
    -------
    left, right, views : int
        Projections whose side stands above :func:`side_bubble_signal`'s level, and the projections in all.
        A foam wider than the detector (local tomography) reaches a side in :data:`LOCAL_VIEWS` of them or more.
    """
    left, right, level = side_bubble_signal(scan.bubble_data, scan.bubble_contrast)
    return int(np.count_nonzero(left > level)), int(np.count_nonzero(right > level)), len(left)


def side_bubble_signal(bubble_data, contrast):
    """The bubbles' signal at the detector's sides, view by view, less a drift common to both sides.

    Parameters
    ----------
    bubble_data : ndarray, ``(views, cols)`` or ``(views, rows, cols)``
        ``data - background``.
    contrast : float
        Bubble contrast, 1/mm (its sign makes the gas's signal positive).

    Returns
    -------
    left, right : (views,) float
        :func:`side_signal` of ``sign(contrast) * bubble_data``, less a
        quadratic over the views fitted to the mean of both sides (its mean
        kept): an offset of whole projections that drifts during the scan is
        removed, a foam wider than the detector (signal at both sides in
        every view) or an off-centre one (at one side in half of them) is not.
    level : float
        The larger of :func:`side_signal`'s noise level and
        :data:`SIDE_FRACTION` of the 99th percentile of the signal.
    """
    values = np.sign(contrast) * np.asarray(bubble_data, dtype=np.float32)
    left, right, noise = side_signal(values)
    if len(left) >= 8:
        x = np.linspace(-1.0, 1.0, len(left))
        drift = np.polynomial.polynomial.polyval(x, np.polynomial.polynomial.polyfit(x, 0.5 * (left + right), 2))
        drift -= drift.mean()
        left, right = left - drift, right - drift
    step = max(1, values.shape[0] // 64)
    return left, right, max(noise, SIDE_FRACTION * float(np.percentile(values[::step], 99)))


#: Most fraction of the values that may pass a bound of :func:`check_physical_signal` by more than the noise
#: before the scan is refused: a few defective detector columns (each 1/cols of the values) stay below it, a
#: signal beyond the physics shows in far more (a foam's data with their sign flipped: all of them).
IMPOSSIBLE_FRACTION = 0.002


#: The region :func:`longest_path` bounds: this times the detector's half-width in the object plane
#: (:data:`bubsub.clients.pipeline.fov.FOV_EXTEND`; fov imports this module, so the value stands here too).
MODELLED_EXTEND = 1.25


def longest_path(geometry):
    """The longest path (mm) a ray of ``geometry`` can take through the region the pipeline models.

    That region is the cylinder of :data:`MODELLED_EXTEND` times the detector's half-width in the object
    plane (the largest over the projections; for a centred detector the preview's region,
    :data:`bubsub.clients.pipeline.fov.FOV_EXTEND` times the field of view's radius): a ray crosses it over
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
    diameter = 2.0 * MODELLED_EXTEND * float(np.max(half_w))
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
    from bubsub.core.prep.background import noise_level

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
    from scipy import ndimage

    size = [1] * mask.ndim
    size[-1] = 2 * margin + 1
    return ~ndimage.maximum_filter(mask, size=size, mode="nearest")
