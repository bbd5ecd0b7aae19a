"""The detector's view-constant term of a local-tomography scan, fitted with the bubbles.

A foam wider than the detector (local tomography,
:func:`bubsub.clients.pipeline.inputs.fov.local_tomography`) has no air at
the detector's sides, so nothing in the data pins the line integrals of a
detector pixel: a column gain error that the flats do not show (a stripe,
a ring in a reconstruction), a background whose liquid profile is a little
too flat or too curved (the fitted radius of
:func:`bubsub.core.prep.background.chord_background`), the foam beyond the
field of view's mean gas; each adds the same amount ``t`` to a detector
pixel in every projection. The fit can explain such a term only with
bubbles, and swells or shifts those whose outline crosses the ring it makes.
(A gain error stays the same in every view only without phase retrieval,
which spreads it by each view's intensity: ``bubsub prepare`` divides such
gains out before the retrieval on these scans, :mod:`bubsub.core.prep.gains`.)

:func:`detector_term_phase` fits the bubbles ``x`` and the term ``t`` (one
value per detector pixel) together. For given bubbles the best term is the
mean over the projections of what they leave, ``t(x) = mean_v (d - P(x))``,
so ``t`` is eliminated exactly (variable projection): the bubbles are
fitted to ``0.5 ||(I - M)(P(x) - d)||^2``, ``M`` the mean over the
projections per detector pixel (:class:`ViewMeanFree`), and ``t(x)`` of
the fitted bubbles is taken from the data. That fit starts twice, from the
seeds and from a plain fit's bubbles, and the start of the lower objective
is kept: a plain fit explains a single column's error (a ring in the
image) with spikes of the bubbles that cross the ring, and a ring being
the same in every view, the elimination barely pulls them back (on seed 11
of ``python -m bubsub.bench fov --local``, a column 0.06 low: interior DDI
0.064 from the plain fit, 0.037 from the seeds, the lower objective;
``tests/test_detector_term.py``); from round seeds alone the elimination
can settle where the plain fit's start does better (seed 21: objective
0.64 from the plain fit, 0.68 from the seeds). A bubble's own
projection moves with the angle, so what every projection shares is the
term's; only a round bubble on the rotation axis projects the same in every
view, and its size then stays the seed's (the data cannot tell it from the
term).

With the term out, the bubble contrast is estimated again
(:func:`term_free_contrast`, as ``bubsub prepare`` estimates it from the data
less the background) and the bubbles refitted with it: the background that
the term corrects also biased the prepared estimate (on seed 5 of ``python -m
bubsub.bench fov --local``, where the fitted liquid radius is furthest off,
-0.107 prepared, -0.103 estimated again, -0.1 true).

The alternative, ``method="alternated"``, is block coordinate descent: the
mean residual is taken from the data and the bubbles refitted from where
they are, ``passes`` times, the first pass's residual taken
:data:`FIRST_STEP` times (the first fit takes about half of a smooth term
into the bubbles). It converges slowly where the bubbles take part of the
term; on the simulated raw scans of ``python -m bubsub.bench fov --local``
(docs/prepare.md) the elimination reaches a lower interior DDI on the scan
whose fitted liquid radius leaves the largest smooth term (seed 5: 0.054,
0.055 with the prepared contrast kept, against 0.066), and leaves the
interior bubbles' mean size within 1.5 % of the truth's on seeds 0-7 (up to
4.5 % wide alternated).
"""

from __future__ import annotations

import numpy as np

from bubsub.clients.optimise.fit import fit
from bubsub.clients.pipeline.inputs.fov import local_tomography
from bubsub.clients.pipeline.regions.local import scene_residual
from bubsub.clients.pipeline.static.repair import merged_validity
from bubsub.core.prep.background import row_geometry, row_phases

__all__ = ["DETECTOR_TERM_METHOD", "DETECTOR_TERM_PASSES", "FIRST_STEP", "TERM_METHODS", "CONTRAST_AGAIN",
           "CONTRAST_CHANGE", "FINAL_REFIT", "NEIGHBOUR_REACH", "ViewMeanFree", "view_constant_residual",
           "term_free_contrast", "detector_term_phase", "added_bubbles_phase", "final_refit_phase"]

#: How the term is fitted with the bubbles: ``"eliminated"`` (variable projection) or ``"alternated"``.
TERM_METHODS = ("eliminated", "alternated")
#: The default of :data:`TERM_METHODS` (``python -m bubsub.bench fov --local``, docs/prepare.md).
DETECTOR_TERM_METHOD = "eliminated"
#: Fits with the term after a plain fit: eliminated, the fits with the term out from each of two starts (the
#: seeds and the plain fit; a second restarts the optimiser where the first stopped); alternated, the passes
#: (docs/prepare.md measured 2).
DETECTOR_TERM_PASSES = 1
#: The alternation's first pass takes its residual this many times: the first fit took about half of the
#: term into the bubbles; the second pass's residual corrects what that over- or undershoots.
FIRST_STEP = 2.0
#: The bubble contrast estimated again from the data less the term, and the bubbles refitted with it.
CONTRAST_AGAIN = True
#: The most the estimate may change the scan's contrast, relative: beyond, the scan's is kept.
CONTRAST_CHANGE = 0.2
#: The last refit of every bubble with the term eliminated (:func:`final_refit_phase`); False: the pipeline without
#: it (the alternative measured, ``python -m bubsub.bench fov --local ... --local-final-refit off``).
FINAL_REFIT = True


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
    return _view_mean_free(projector, surfaces, data)[1]


class ViewMeanFree:
    """A projector's data term with the view-constant term eliminated: ``0.5 ||(I - M)(P(x) - d)||^2``.

    ``M`` takes the mean over the projections per detector pixel. The minimum
    over a term ``t`` per detector pixel of ``0.5 ||P(x) + t - d||^2`` lies at
    ``t(x) = mean_v (d - P(x))``, so this is the plain data term on
    ``d - t(x)``, and, ``t(x)`` being that minimiser, so is its gradient (one
    projection for ``t(x)``, then the projector's fused objective).

    Parameters
    ----------
    projector : MeshProjector
        Of the fitted projections; ``geometry``, ``supersampling``, ``threads`` and ``backend`` are its.
    """

    def __init__(self, projector):
        self.projector = projector
        self.geometry = projector.geometry
        self.supersampling = projector.supersampling
        self.threads = projector.threads
        self.backend = projector.backend

    def __repr__(self):
        return f"ViewMeanFree({self.projector!r})"

    def forward(self, surfaces, deadline=None):
        """The wrapped projector's projections, ``geometry.shape``."""
        return self.projector.forward(surfaces, deadline)

    def objective(self, surfaces, data, deadline=None):
        """``f = 0.5 ||(I - M)(P(x) - d)||^2`` and its gradient per surface (``MeshProjector.objective``'s).

        Parameters
        ----------
        surfaces : list of SubdivisionSurface
        data : ndarray, ``geometry.shape``
        deadline : float, optional

        Returns
        -------
        f : float
        grads : list of (n_i, 3) or (n_i, 2) float
        """
        d = np.asarray(data, dtype=np.float64)
        term = (d - np.asarray(self.projector.forward(surfaces, deadline), dtype=np.float64)).mean(axis=0)
        return self.projector.objective(surfaces, (d - term[None]).astype(data.dtype), deadline)


def term_free_contrast(data, geometry):
    """The bubble contrast from an FBP of the middle detector row of ``data`` (the bubbles' signal, the
    detector term taken out): the gas's attenuation less the liquid's, each phase eroded by 2 pixels
    (:func:`bubsub.core.prep.background.row_phases`, as ``bubsub prepare`` estimates it on data less
    the background), inside 0.9 of the field of view's radius.

    Parameters
    ----------
    data : ndarray, ``geometry.shape``
        ``(views, cols)`` or ``(views, rows, cols)``.
    geometry : ScanGeometry
        Parallel beam.

    Returns
    -------
    float or None
        1/mm; None for a cone or fan beam, or where the slice holds too few gas or liquid pixels.
    """
    if geometry.is_cone:
        return None
    row = data if geometry.ndim == 2 else data[:, geometry.det_rows // 2]
    try:
        liquid, gas = row_phases(row, row_geometry(geometry))
    except ValueError:
        return None
    return gas - liquid


def _view_mean_free(projector, surfaces, data):
    """``0.5 ||(I - M)(P(x) - d)||^2`` (:class:`ViewMeanFree`'s objective, without its gradient) and the term
    ``t(x) = mean_v (d - P(x))`` (:func:`view_constant_residual`'s, float32), from one projection."""
    residual = scene_residual(projector, surfaces, data)
    term = -residual.mean(axis=0)
    residual += term[None]
    return 0.5 * float(np.vdot(residual, residual)), term.astype(np.float32)


def _rms(a):
    """Root mean square, in float64."""
    return float(np.sqrt(np.mean(np.square(a, dtype=np.float64))))


def detector_term_phase(run, surfaces, refit, contrast, *, enabled=True, passes=None, method=None,
                        contrast_again=None):
    """The pipeline's fit, with the detector's view-constant term where the scan is local tomography (see the
    module docstring); elsewhere the plain fit of ``surfaces``, and nothing else changes, not even the report.

    Parameters
    ----------
    run : bubsub.clients.pipeline.reconstruct.PhaseContext
        Its ``data`` are replaced by the data less the term; its report gets
        ``detector_term``: ``method``, ``passes`` (fits with the term), ``rms`` (the term's root mean square)
        and, eliminated, ``start`` (the one kept) and ``starts`` (each one's ``objective`` and ``term_rms``).
        Its ``projector`` is a :class:`ViewMeanFree` during an eliminated fit, and is restored after.
    surfaces : list of SubdivisionSurface
        The seeds.
    refit : callable(run, surfaces) -> _Fit
        Fits ``surfaces`` to ``run.data`` with ``run.projector`` (the pipeline's fit phase).
    contrast : float
        Bubble contrast.
    enabled : bool
        False: the plain fit (the field-of-view model off, or a remote projector that holds its data).
    passes : int, optional
        Default :data:`DETECTOR_TERM_PASSES` (read at the call): eliminated, the fits with the term out from
        each start (the seeds and the plain fit), each next from the last, the start whose last fit has the
        lower objective kept; alternated, the passes after the plain fit; 0: the plain fit alone (the report
        says so).
    method : {"eliminated", "alternated"}, optional
        Default :data:`DETECTOR_TERM_METHOD` (read at the call).
    contrast_again : bool, optional
        Default :data:`CONTRAST_AGAIN` (read at the call): once the term is out, the contrast is estimated
        again (:func:`term_free_contrast`) and, where it changed by at most :data:`CONTRAST_CHANGE`, the
        bubbles take it and are refitted once more (as ``method`` refits); the report's ``contrast_per_mm``
        is the contrast the bubbles have, ``contrast_estimated_per_mm`` the estimate (None: none).

    Returns
    -------
    fit : _Fit
        The last fit; a fit interrupted or without bubbles ends the phase.
    term : ndarray float32, ``run.data.shape[1:]``, or 0.0
        What was taken from each detector pixel (to take from held-out projections too); 0.0 when
        nothing was done.
    contrast : float
        The bubbles' contrast from here on: ``contrast`` unless estimated again.
    """
    method = DETECTOR_TERM_METHOD if method is None else method
    if method not in TERM_METHODS:
        raise ValueError(f"the detector term's method must be one of {TERM_METHODS}, got {method!r}")
    if not enabled or not local_tomography(run.data, contrast):
        return refit(run, surfaces), 0.0, contrast
    passes = DETECTOR_TERM_PASSES if passes is None else passes
    term = np.zeros(run.data.shape[1:], dtype=np.float32)

    def take(step):
        nonlocal term
        term += step
        run.data = (run.data - step[None]).astype(run.data.dtype)

    def one_refit(surfaces, k):
        step = view_constant_residual(run.projector, surfaces, run.data)
        if method == "alternated":
            take(step * (FIRST_STEP if k == 0 else 1.0))
            return refit(run, surfaces)
        take(step)  # the data less the term so far for binned levels (3D), where the projector is not wrapped
        projector, run.projector = run.projector, ViewMeanFree(run.projector)
        try:
            out = refit(run, surfaces)
        finally:
            run.projector = projector
        take(view_constant_residual(run.projector, out.surfaces, run.data))  # t(x) of the refitted bubbles
        return out

    plain = refit(run, surfaces)
    entry = {"method": method}
    if method == "alternated" or passes == 0 or plain.interrupted or not plain.surfaces:
        fit, done = plain, 0
        for k in range(passes):
            if fit.interrupted or not fit.surfaces:
                break
            fit = one_refit(fit.surfaces, k)
            done += 1
    else:
        # eliminated, from two starts, the one of the lower objective kept: the seeds (a plain fit explains a
        # column error's ring with spikes of the bubbles that cross it, which the elimination, a ring being the
        # same in every view, barely pulls back) and the plain fit (from round seeds alone the elimination can
        # settle in a degenerate state: bubbles drawn to the axis, whose projection is nearly the same in every
        # view, the term taking the rest)
        data, tries = run.data, []
        for name, start in (("seeds", surfaces), ("plain fit", plain.surfaces)):
            run.data, term = data, np.zeros(data.shape[1:], dtype=np.float32)
            fit, done = None, 0
            for k in range(passes):
                if fit is not None and (fit.interrupted or not fit.surfaces):
                    break
                fit = one_refit(start if fit is None else fit.surfaces, k)
                done += 1
            f = ViewMeanFree(run.projector).objective(fit.surfaces, data)[0] if fit.surfaces else np.inf
            tries.append((f, name, fit, run.data, term, done))
            if fit.interrupted:
                break
        _, entry["start"], fit, run.data, term, done = min(tries, key=lambda t: t[0])
        entry["starts"] = {name: {"objective": float(f), "term_rms": _rms(t)} for f, name, _, _, t, _ in tries}
    entry["passes"] = done
    if (CONTRAST_AGAIN if contrast_again is None else contrast_again) and done:
        estimate = term_free_contrast(run.data, run.projector.geometry)
        entry["contrast_estimated_per_mm"] = estimate
        if (estimate is not None and not fit.interrupted and fit.surfaces and estimate * contrast > 0
                and abs(estimate / contrast - 1) <= CONTRAST_CHANGE):
            contrast = float(estimate)
            fit = one_refit([x.with_attenuation(contrast) for x in fit.surfaces], done)
    entry["contrast_per_mm"] = float(contrast)
    entry["rms"] = _rms(term)
    run.report["detector_term"] = entry
    return fit, term, contrast


#: A neighbour of an added bubble, refitted with it by :func:`added_bubbles_phase`: a bubble whose centre lies within
#: both radii and this many median bubble radii of the added one's.
NEIGHBOUR_REACH = 2.0


def added_bubbles_phase(run, surfaces, changes, *, iterations, penalty=None, progress=False):
    """After the topology rounds of a local-tomography scan: the bubbles they added, with their neighbours, refitted
    with the detector's view-constant term eliminated, the rest held, and the term taken again from all bubbles.

    The term was taken from the data before those bubbles existed, so what every projection shares of an added
    bubble's signal is already out of the data: fitted against it, an added bubble stays small where its
    projection changes little between the views, near the rotation axis (seed 56 of ``python -m bubsub.bench fov
    --local``: a bubble of 0.12 mm radius 0.12 mm from the axis, added at 0.05 mm; refitted so, it and its
    neighbours take the interior DDI from 0.063 to 0.054, the bubble found). A scan that fits the detector, or
    rounds that added nothing, leave everything as it was.

    Parameters
    ----------
    run : bubsub.clients.pipeline.reconstruct.PhaseContext
        Its ``data`` (less the term so far) lose the term's further step; its report's ``detector_term`` gets
        ``after_topology``: the bubbles refitted and the eliminated objective before and after; its clock marks
        ``added_bubbles`` when the refit ran.
    surfaces : list of SubdivisionSurface
    changes : list of dict
        The topology rounds' changes (their ``change`` and ``centre``).
    iterations : int
        BFGS iterations of the refit.
    penalty : callable, optional
        As for :func:`bubsub.clients.optimise.fit.fit`.
    progress : bool

    Returns
    -------
    surfaces : list of SubdivisionSurface
    step : ndarray float32, ``run.data.shape[1:]``, or 0.0
        What was taken from each detector pixel besides the term so far.
    """
    added = [np.asarray(c["centre"], dtype=float) for c in changes if c.get("change") == "add"]
    entry = run.report.get("detector_term")
    if not added or not surfaces or entry is None or not entry.get("passes"):
        return surfaces, 0.0
    fine = [x.fine() for x in surfaces]
    centres = np.array([f.vertices.mean(axis=0) for f in fine])
    radii = np.array([f.equivalent_radius for f in fine])
    new = {int(np.argmin(np.linalg.norm(centres - c, axis=1))) for c in added}
    reach = NEIGHBOUR_REACH * float(np.median(radii))
    ids = sorted({j for k in new for j in range(len(surfaces))
                  if np.linalg.norm(centres[j] - centres[k]) < radii[j] + radii[k] + reach})
    out, step, refit = _eliminated_refit(run, surfaces, ids, iterations=iterations, penalty=penalty,
                                         progress=progress, label="refit of the added bubbles, term eliminated")
    if refit is not None:
        entry["after_topology"] = dict(refit, added=len(new))
    run.clock.mark("added_bubbles")
    return out, step


def final_refit_phase(run, surfaces, repair, *, iterations, penalty=None, progress=False):
    """The last fit of a local-tomography scan: every bubble refitted with the detector's view-constant term
    eliminated, the term taken again, and the bubbles checked and repaired once more.

    Some bubbles leave the fits with spikes whose control polygon or mesh crosses itself; the repair smooths them,
    moving control vertices by up to a quarter of a millimetre, and its refits, like the topology rounds' and the
    refinement's, are plain fits against the data less the term as the elimination left it, so what the term took
    of the bubbles it was taken from stays out of the data whatever they do (seed 17 of ``python -m bubsub.bench
    fov --local``: interior DDI 0.044 after the topology rounds, 0.053 after the repair). Refitted with the term
    eliminated, the bubbles settle where the elimination puts them (seed 17: 0.034); over the 60 scans of that
    benchmark the final refit moves the interior DDI by -0.019 to +0.002 (docs/prepare.md).

    Parameters
    ----------
    run : bubsub.clients.pipeline.reconstruct.PhaseContext
        Its ``data`` (less the term so far) lose the term's further step; its report's ``detector_term`` gets
        ``final_refit`` (the bubbles refitted, the eliminated objective before and after, the step's root mean
        square) and its ``validity`` the second check's findings (:func:`~.repair.merged_validity`, stage
        ``"after the final refit"``); its clock marks ``final_refit`` when the refit ran.
    surfaces : list of SubdivisionSurface
    repair : callable(surfaces) -> (surfaces, summary)
        The pipeline's check and repair (:func:`~.repair.check_and_repair` with its options).
    iterations, penalty, progress
        As for :func:`added_bubbles_phase`.

    Returns
    -------
    surfaces, step
        As :func:`added_bubbles_phase`'s; ``step`` is 0.0 where the scan has no term, the
        refit did not lower the objective (the bubbles then stay as they were, unchecked again) or
        :data:`FINAL_REFIT` (read at the call) is False.
    """
    entry = run.report.get("detector_term")
    if not FINAL_REFIT or not surfaces or entry is None or not entry.get("passes"):
        return surfaces, 0.0
    out, step, refit = _eliminated_refit(run, surfaces, range(len(surfaces)), iterations=iterations, penalty=penalty,
                                         progress=progress, label="final refit, term eliminated")
    if refit is None:
        run.clock.mark("final_refit")
        return surfaces, 0.0
    entry["final_refit"] = refit
    out, again = repair(out)
    if "validity" in run.report:
        run.report["validity"] = merged_validity(run.report["validity"], again, stage="after the final refit")
    run.clock.mark("final_refit")
    return out, step


def _eliminated_refit(run, surfaces, ids, *, iterations, penalty, progress, label):
    """The bubbles ``ids`` of ``surfaces`` refitted with the term eliminated (:class:`ViewMeanFree`), the others
    held: where that lowers the eliminated objective of all of them, the term is taken again from ``run.data``.
    Ctrl-C is not caught: the pipeline reports the bubbles as they were.

    Returns
    -------
    surfaces : list of SubdivisionSurface
        ``surfaces`` with the refitted ones; ``surfaces`` itself where the objective did not fall.
    step : ndarray float32, ``run.data.shape[1:]``, or 0.0
        The term's further step, taken from ``run.data``.
    entry : dict or None
        ``refitted``, ``objective_before``, ``objective_after``, ``term_step_rms``; None where nothing changed.
    """
    ids = list(ids)
    refitted = set(ids)
    rest = -scene_residual(run.projector, [x for j, x in enumerate(surfaces) if j not in refitted], run.data)
    before, _ = _view_mean_free(run.projector, surfaces, run.data)
    result = fit(ViewMeanFree(run.projector), [surfaces[j] for j in ids], rest.astype(run.data.dtype),
                 iterations=iterations, penalty=penalty, progress=progress, catch_interrupt=False, label=label)
    out = list(surfaces)
    for j, x in zip(ids, result.surfaces):
        out[j] = x
    after, step = _view_mean_free(run.projector, out, run.data)
    if not after < before:
        return surfaces, 0.0, None
    run.data = (run.data - step[None]).astype(run.data.dtype)
    return out, step, {"refitted": len(ids), "objective_before": float(before), "objective_after": float(after),
                       "term_step_rms": _rms(step)}
