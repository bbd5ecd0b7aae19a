"""Whether the bubbles reach the detector's sides: a few bubbles beyond the field of view, or a foam wider
than the detector (local tomography).

Judged from the bubbles' signal ``data - background`` at the outermost columns (the liquid, held by the
background, is harmless); it warns or notes and never refuses: the field-of-view model
(:mod:`bubsub.clients.pipeline.inputs.fov`) reconstructs such scans.
"""

from __future__ import annotations

import logging
import weakref

import numpy as np

__all__ = ["check_lateral_truncation", "side_signal", "side_bubble_signal", "side_hits", "TRUNCATED_VIEWS",
           "LOCAL_VIEWS", "SIDE_FRACTION", "SIDE_COLUMNS"]


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
    (:data:`bubsub.clients.pipeline.inputs.fov.FOV_EXTEND`) and, through
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
