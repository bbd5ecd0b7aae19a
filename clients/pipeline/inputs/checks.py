"""Checks run before a reconstruction computes anything: settings and the scan's bubble signal.

The scan's physics (:mod:`bubsub.clients.pipeline.inputs.physics`) and its detector's sides
(:mod:`bubsub.clients.pipeline.inputs.sides`) each have a module of their own.

Each takes well under a second and raises ``ValueError`` with one line that
names the problem and the fix, so that a mistake costs seconds, not a fit,
and never yields a silent wrong result.
"""

from __future__ import annotations

import numpy as np

from bubsub.clients.pipeline.inputs.physics import check_physical_signal
from bubsub.clients.pipeline.inputs.sides import check_lateral_truncation
from bubsub.core.contrast import signal_masses
from bubsub.core.validate import check_int

__all__ = ["check_setting_values", "check_settings", "check_bubble_signal", "CONTROL_POINTS_3D", "MAX_LEVELS"]

#: Control vertices of the icosphere control meshes (3D bubbles).
CONTROL_POINTS_3D = (12, 42, 162)
#: Subdivision levels beyond this cost far more than they add (4**levels faces per control face).
MAX_LEVELS = 4


def check_setting_values(settings):
    """Refuse reconstruction settings that no scan accepts (``ReconstructionSettings.__post_init__`` runs it).

    Parameters
    ----------
    settings : ReconstructionSettings

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


def check_settings(settings, ndim):
    """Refuse reconstruction settings that cannot work for a ``ndim``-D scan: the checks that need the scan's
    dimension (the others ran when the settings were made, :func:`check_setting_values`).

    Parameters
    ----------
    settings : ReconstructionSettings
    ndim : {2, 3}

    Raises
    ------
    ValueError
        Naming the setting (as its command-line option) and the allowed values.
    """
    cp = settings.control_points
    if ndim == 3 and cp is not None and cp not in CONTROL_POINTS_3D:
        raise ValueError(f"--control-points must be one of {list(CONTROL_POINTS_3D)} for a 3D scan "
                         f"(icosphere control meshes), got {cp}")


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
