"""The detector's view-constant term of a local-tomography scan, fitted with the bubbles.

A foam wider than the detector (local tomography,
:func:`bubsub.clients.pipeline.inputs.fov.local_tomography`) has no air at
the detector's sides, so nothing in the data pins the line integrals of a
detector pixel: a column gain error that the flats do not show (a stripe,
a ring in a reconstruction), a background whose liquid profile is a little
too flat or too curved (the fitted radius of
:func:`bubsub.core.prep.background.chord_background`), the foam beyond the
field of view's mean gas; each adds the same amount to a detector pixel in
every projection. The fit can explain such a term only with bubbles, and
swells or shifts those whose outline crosses the ring it makes.

:func:`detector_term_phase` alternates the two: after the fit, the mean over
the projections of what the bubbles leave (``data - P(bubbles)``, per
detector pixel) is taken from the data, and the bubbles are fitted again
from where they are; :data:`DETECTOR_TERM_PASSES` times. The first fit
takes part of the term into the bubbles, and its residual shows only the
rest: on the scans below the second residual against the first (their
inner product over the first's square) is 0.52-0.53 for the residual's
smooth part (a Gaussian of 4 pixels) and 0.20-0.25 for the rest, so the
first pass takes its residual :data:`FIRST_STEP` times and the second
corrects the over- or undershoot (where the fit takes none, the first pass
takes twice the term and the second takes the excess back).
A bubble's own
projection moves with the angle, so its misfit averages out over a
180-degree scan; the term keeps only what every projection shares. On the
simulated raw scans of ``python -m bubsub.bench fov --local`` (docs/prepare.md)
the mean over the projections of the data's error against the exact
projection of the true bubbles has a root mean square of 0.006-0.009 (the
bubbles' chords reach 0.04); taking that exact term out brings the
interior DDI of seeds 5-7 from 0.060-0.081 to 0.030-0.042 with the liquid's
exact projection as background.
"""

from __future__ import annotations

import numpy as np

from bubsub.clients.pipeline.inputs.fov import local_tomography

__all__ = ["DETECTOR_TERM_PASSES", "FIRST_STEP", "view_constant_residual", "detector_term_phase"]

#: Fits after the first, each after taking out the view-constant residual the previous one left
#: (``python -m bubsub.bench fov --local``, docs/prepare.md).
DETECTOR_TERM_PASSES = 2
#: The first pass's residual is taken this many times: the first fit took about half of the term into the
#: bubbles (see the module docstring); the second pass's residual corrects what that over- or undershoots.
FIRST_STEP = 2.0


def view_constant_residual(projector, surfaces, data):
    """Mean over the projections of the data less the bubbles' projection.

    Parameters
    ----------
    projector : MeshProjector
        Of the fitted projections.
    surfaces : list of SubdivisionSurface
    data : ndarray, ``projector.geometry.shape``
        ``(views, cols)`` or ``(views, rows, cols)``, bubbles' signal.

    Returns
    -------
    ndarray float32, ``data.shape[1:]``
        Per detector pixel: ``(cols,)`` or ``(rows, cols)``.
    """
    rest = np.asarray(data, dtype=np.float64) - np.asarray(projector.forward(surfaces), dtype=np.float64)
    return rest.mean(axis=0).astype(np.float32)


def detector_term_phase(run, fit, refit, contrast, *, enabled=True, passes=None):
    """Fit the detector's view-constant term with the bubbles where the scan is local tomography (see the
    module docstring); elsewhere nothing changes, not even the report.

    Parameters
    ----------
    run : bubsub.clients.pipeline.reconstruct.PhaseContext
        Its ``data`` are replaced by the data less the term; its report gets
        ``detector_term``: ``passes`` and ``rms`` (the term's root mean square).
    fit : bubsub.clients.pipeline.reconstruct._Fit
        The first fit, on ``run.data``.
    refit : callable(run, surfaces) -> _Fit
        Fits ``surfaces`` to ``run.data`` (the pipeline's fit phase).
    contrast : float
        Bubble contrast.
    enabled : bool
        False: nothing is done (the field-of-view model off, or a remote projector that holds its data).
    passes : int, optional
        Default :data:`DETECTOR_TERM_PASSES` (read at the call).

    Returns
    -------
    fit : _Fit
        The last fit; ``fit`` itself when it was interrupted or found no bubbles.
    term : ndarray float32, ``run.data.shape[1:]``, or 0.0
        What was taken from each detector pixel (to take from held-out projections too); 0.0 when
        nothing was done.
    """
    if not enabled or not local_tomography(run.data, contrast):
        return fit, 0.0
    term = np.zeros(run.data.shape[1:], dtype=np.float32)
    done = 0
    for k in range(DETECTOR_TERM_PASSES if passes is None else passes):
        if fit.interrupted or not fit.surfaces:
            break
        step = view_constant_residual(run.projector, fit.surfaces, run.data) * (FIRST_STEP if k == 0 else 1.0)
        term += step
        run.data = (run.data - step[None]).astype(run.data.dtype)
        fit = refit(run, fit.surfaces)
        done += 1
    run.report["detector_term"] = {"passes": done, "rms": float(np.sqrt(np.mean(term.astype(np.float64) ** 2)))}
    return fit, term
