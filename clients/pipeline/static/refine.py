"""Coarse-to-fine: refine every control mesh once and refit, kept when the data say so.

A control mesh of 42 vertices (3D) or 9 points (2D) fits a round bubble, but
not the flat films and Plateau borders (2 voxels of curvature radius) of a
dense foam's polyhedral cells: on the quick dense 3D foam the best fit from
the true shapes stays at about twice the noise's objective. Starting with
more control vertices lets the early, far-from-converged iterations tangle
the meshes (docs/robustness.md). So the pipeline fits the coarse meshes
first, then moves one subdivision step into each control mesh
(:func:`bubsub.core.projection.subdivision.refine_control`: the surface is
unchanged, vertex for vertex, at one level less) and continues the fit with
four (3D) or two (2D) times the unknowns.

The refined fit is kept only when it lowers the Akaike score
``m log(2 f / m) + 2 k`` (:func:`bubsub.clients.optimise.criteria.akaike_score`)
of the coarse one: more unknowns must explain more of the data than noise
would. Round, well separated bubbles gain little and stay coarse; the
refined fit stops after ``trial`` iterations (10) when it has not yet paid
for its unknowns, so they cost little time; from half the trial on it stops
as soon as the bar is out of reach at its own best pace (:func:`out_of_reach`). That trial is measured against
what the coarse fit would have reached in as many more iterations at the
pace it ended with (:func:`coarse_rate`): a coarse fit stopped by its
iteration cap still gains each iteration, and a refined fit would otherwise
be kept, and run to its own cap with four times the unknowns, for progress
the coarse bubbles would have made too.
"""

from __future__ import annotations

import numpy as np

from bubsub.core.projection.subdivision import refine_control

from bubsub.clients.optimise.criteria import akaike_score
from bubsub.clients.optimise.fit import fit
from bubsub.clients.pipeline.regions.local import scene_objective

__all__ = ["refine_and_fit", "refine_and_check", "can_refine", "refinable", "coarse_rate", "out_of_reach",
           "penalised_objective", "control_counts"]


#: The refined fit's stop reason when its trial fails: the finer surfaces did not lower the objective enough,
#: within a few iterations, to pay for their extra unknowns (the coarse bubbles are kept).
TRIAL_FAILED = "stopped: the finer surfaces do not pay for their extra unknowns"

def refinable(surface):
    """Whether a bubble has a subdivision level to move into its control mesh, keeping one in 3D.

    A 3D control mesh left without a subdivision level is its own fine mesh, every vertex moved by the
    fit on its own, and such meshes fold (bubbles small enough to have one level, :mod:`.resolution`). A
    bubble that small has a control vertex every 4 pixels or so already.
    """
    return surface.levels >= (2 if surface.ndim == 3 else 1)


def control_counts(surfaces):
    """Bubbles per number of control points (2D) or vertices (3D), ``{"9": n9, "18": n18, ...}``
    (report.json's ``control_points``): a kept refinement doubles a 2D polygon's points (9 -> 18) and takes a
    3D icosphere from 42 to 162 vertices, each with one subdivision level less."""
    counts = {}
    for s in surfaces:
        k = str(len(s.vertices))
        counts[k] = counts.get(k, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: int(kv[0])))


def can_refine(surfaces):
    """Whether any surface is :func:`refinable`."""
    return any(refinable(s) for s in surfaces)


def coarse_rate(history, window=5):
    """Objective decrease per iteration over a fit's last ``window`` iterations (0 for shorter fits).

    Parameters
    ----------
    history : list of dict
        :attr:`bubsub.clients.optimise.fit.FitResult.history`.
    """
    if len(history) <= window:
        return 0.0
    return max(0.0, (history[-window - 1]["objective"] - history[-1]["objective"]) / window)


def out_of_reach(history, bar, left):
    """Whether a fit whose objectives so far are ``history`` (its start first) cannot get below ``bar`` in
    ``left`` more iterations without an iteration better than its best so far.

    On a tomography-size scan the refinement's bar is far off (42 -> 162 control vertices per bubble
    need the objective several percent lower, docs/large-scans.md), and the trial's last iterations, each a
    projection of the whole scan, would change nothing. Quasi-Newton iterations slow down as a fit proceeds, so a fit that would need its best
    iteration's drop, or more, every iteration from here on is not going to make it.
    """
    drops = -np.diff(np.asarray(history, dtype=float))
    best = float(drops.max()) if drops.size else 0.0
    return history[-1] - bar > left * max(best, 0.0)


def penalised_objective(projector, surfaces, data, penalty=None, data_term=None):
    """``0.5 ||Proj(S x) - d||^2`` of ``surfaces`` (``data_term`` when already known), plus ``penalty``'s term.

    Parameters
    ----------
    projector : MeshProjector
        Of ``data``.
    surfaces : list of SubdivisionSurface
    data : ndarray
    penalty : callable, optional
        As :func:`bubsub.clients.optimise.fit.fit`'s.
    data_term : float, optional
        The data term of ``surfaces``, if known (no projection is made then).
    """
    f = scene_objective(projector, surfaces, data) if data_term is None else float(data_term)
    if penalty is not None and surfaces:
        f += float(penalty([s.vertices for s in surfaces])[0])
    return f


def refine_and_fit(projector, surfaces, data, *, iterations, trial=10, penalty=None, progress=False, rtol=None,
                   coarse_rate=0.0, reached=None):
    """Refine the control meshes once, fit, and keep the result if its Akaike score is lower.

    Parameters
    ----------
    projector : MeshProjector
        Of ``data``.
    surfaces : list of SubdivisionSurface
        The coarse fit's bubbles; the :func:`refinable` ones are refined, the others kept as they are.
    data : ndarray
        The fitted projections.
    iterations : int
        BFGS iterations of the refined fit.
    trial : int
        After this many iterations the fit stops unless its Akaike score is
        already below the coarse one (so round bubbles cost only ``trial``
        iterations); from ``trial // 2`` iterations on it stops once that is
        :func:`out_of_reach`.
    penalty : callable, optional
        As :func:`bubsub.clients.optimise.fit.fit`'s (it works on any control topology).
    rtol : float, optional
        The refined fit's convergence test (:func:`bubsub.clients.optimise.fit.fit`).
    coarse_rate : float
        How much the coarse fit's objective still fell per iteration when it
        stopped (:func:`coarse_rate`). The trial must beat the coarse
        objective less ``trial`` times this: a coarse fit stopped by its
        iteration cap would gain as much by going on, and the refinement
        must be worth more than that.
    reached : float, optional
        The data term ``0.5 ||Proj(S x) - d||^2`` the coarse bubbles had before a
        repair that preceded the refinement: the trial starts from their objective
        less the repair's rise in that term. A repair's separations raise the data
        term by what any refit regains, coarse or refined: measured from the
        raised objective, a refined fit would pass its trial merely by regaining
        it, run all its iterations over the whole scan, and lose the advantage
        to its own repair (docs/scale.md, the ~2400-bubble column).

    Returns
    -------
    surfaces : list of SubdivisionSurface
        The refined bubbles, or ``surfaces`` unchanged.
    summary : dict
        ``kept`` (bool), ``objective_before``/``after``, ``objective_reached`` (the trial's start:
        ``objective_before`` less the repair's rise, with ``reached``), ``score_before``/``after``,
        ``bubbles_refined``, ``control_vertices_before``/``after`` (the most of a bubble), ``iterations``,
        ``evaluations``, ``stop_reason`` (of the refined fit).
    """
    surfaces = list(surfaces)
    if not can_refine(surfaces):
        raise ValueError("refining needs a surface with a subdivision level to spare (two in 3D)")
    data = np.asarray(data)
    data0 = scene_objective(projector, surfaces, data)
    f0 = penalised_objective(projector, surfaces, data, penalty, data0)
    refined = [refine_control(s) if refinable(s) else s for s in surfaces]
    m, k = data.size, sum(s.vertices.size for s in refined)
    k0 = sum(s.vertices.size for s in surfaces)
    before = akaike_score(f0, m, k0)
    # what the coarse bubbles would reach in as many more iterations of their own fit
    start = f0 if reached is None else f0 - max(0.0, data0 - float(reached))
    before_trial = akaike_score(max(start - trial * max(float(coarse_rate), 0.0), 1e-300), m, k0)

    # the objective that scores before_trial with the refined unknowns (akaike_score solved for f)
    bar = 0.5 * m * np.exp((before_trial - 2.0 * k) / m)
    seen = [f0]

    def trial_failed(iteration, objective, _):
        # a refinement that has not paid for its unknowns after a few iterations is not worth the rest
        seen.append(objective)
        if iteration == trial:
            failed = akaike_score(objective, m, k) >= before_trial
        else:
            failed = trial // 2 <= iteration < trial and out_of_reach(seen, bar, trial - iteration)
        return TRIAL_FAILED if failed else None

    result = fit(projector, refined, data, iterations=iterations, progress=progress, catch_interrupt=False,
                 penalty=penalty, label="refined fit", callback=trial_failed, rtol=rtol)
    after = akaike_score(result.objective, m, k)
    # a refinement stopped by the trial is judged by the trial's own bar
    kept = after < (before_trial if result.stop_reason == TRIAL_FAILED else before)
    summary = {"kept": bool(kept), "objective_before": f0, "objective_reached": start,
               "objective_after": result.objective,
               "coarse_rate": float(coarse_rate), "stop_reason": result.stop_reason,
               "score_before": before, "score_after": after, "iterations": result.iterations,
               "evaluations": result.evaluations,
               "bubbles_refined": sum(a is not b for a, b in zip(refined, surfaces)),
               "control_vertices_before": max(len(x.vertices) for x in surfaces),
               "control_vertices_after": max(len(x.vertices) for x in refined)}
    return (result.surfaces if kept else surfaces), summary


def refine_and_check(projector, surfaces, data, check, *, iterations, penalty=None, progress=False, rtol=None,
                     coarse_rate=0.0, reached=None):
    """:func:`refine_and_fit`, then ``check`` (the pipeline's validity check and repair) on a kept result,
    whose Akaike score must still beat the coarse one's afterwards (else the valid coarse bubbles stay).

    Parameters
    ----------
    check : callable(list of SubdivisionSurface) -> (surfaces, validity summary)

    Returns
    -------
    surfaces : list of SubdivisionSurface
    summary : dict
        :func:`refine_and_fit`'s, plus ``score_after_repair`` when checked; ``kept`` is False
        when the repair cost the refinement its advantage (a dropped bubble).
    validity : dict or None
        ``check``'s summary of the kept refined bubbles.
    """
    refined, summary = refine_and_fit(projector, surfaces, data, iterations=iterations, penalty=penalty,
                                      progress=progress, rtol=rtol, coarse_rate=coarse_rate, reached=reached)
    if not summary["kept"]:
        return surfaces, summary, None
    repaired, validity = check(refined)
    f = penalised_objective(projector, repaired, data, penalty) if repaired else float("inf")
    summary["score_after_repair"] = akaike_score(f, np.asarray(data).size, sum(s.vertices.size for s in repaired))
    if not summary["score_after_repair"] < summary["score_before"]:
        summary["kept"] = False
        return surfaces, summary, None
    return repaired, summary, validity
