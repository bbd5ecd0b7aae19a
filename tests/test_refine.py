"""Coarse-to-fine refinement: the refined control mesh keeps the surface, and the refit is kept only when it pays."""

import numpy as np
import pytest

from bubsub.clients.optimise.criteria import akaike_score
from bubsub.clients.pipeline.static.refine import TRIAL_FAILED, can_refine, refine_and_fit
from bubsub.core import MeshProjector, ScanGeometry, circle_surface, sphere_surface
from bubsub.core.projection.mesh import Polygon
from bubsub.core.projection.subdivision import refine_control

MU = -0.1


@pytest.mark.parametrize("make, centre, count", [(sphere_surface, [0.2, -0.1, 0.3], 162),
                                                 (circle_surface, [0.2, -0.1], 18)])
def test_refined_control_mesh_keeps_the_fine_surface_vertex_for_vertex(make, centre, count):
    rng = np.random.default_rng(0)
    s = make(centre, 1.0, MU)
    s = s.with_vertices(s.vertices + 0.1 * rng.standard_normal(s.vertices.shape))  # not a sphere: a real test
    r = refine_control(s)
    assert len(r.vertices) == count and r.levels == s.levels - 1 and r.attenuation == MU
    np.testing.assert_allclose(r.fine().vertices, s.fine().vertices, atol=1e-9)
    if s.ndim == 3:
        np.testing.assert_array_equal(np.asarray(r.fine().faces), np.asarray(s.fine().faces))
    # at the same level the fine mesh is finer but the limit surface is the same: volumes (areas) agree closely
    finer = refine_control(s, levels=s.levels).fine()
    size = (lambda f: f.volume if s.ndim == 3 else f.area)
    assert len(finer.vertices) > len(s.fine().vertices)
    assert size(finer) == pytest.approx(size(s.fine()), rel=0.02)
    assert not can_refine([refine_control(s, levels=0)])
    # a 3D bubble keeps one subdivision level: one at a single level is not refined
    assert can_refine([s.with_levels(2)]) and (can_refine([s.with_levels(1)]) == (s.ndim == 2))


def _rounded_square(centre, half, rho, n=256):
    t = 2 * np.pi * np.arange(n) / n
    u = np.stack([np.cos(t), np.sin(t)], axis=1)
    corners = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * (half - rho)
    support = corners[np.argmax(u @ corners.T, axis=1)]  # the support point of the inner square, plus rho u
    return Polygon(np.asarray(centre) + support + rho * u, MU)


def _scan(truth, seed=0, sigma=0.002):
    geometry = ScanGeometry.parallel(np.linspace(0, np.pi, 20, endpoint=False), cols=128, pixel_size=0.05)
    projector = MeshProjector(geometry)
    clean = projector.forward(truth)
    return projector, clean + sigma * np.random.default_rng(seed).standard_normal(clean.shape).astype(np.float32)


def _coarse_fit(projector, data, centres, radius):
    from bubsub.clients.optimise.fit import fit

    start = [circle_surface(c, radius, MU) for c in centres]
    return fit(projector, start, data, iterations=60, progress=False).surfaces


def test_refit_of_square_bubbles_is_kept_and_fits_better():
    centres = ([-1.2, 0.0], [1.1, 0.3])
    projector, data = _scan([_rounded_square(c, 0.9, 0.15) for c in centres])
    coarse = _coarse_fit(projector, data, centres, 0.9)
    out, summary = refine_and_fit(projector, coarse, data, iterations=30)
    assert summary["kept"] and summary["score_after"] < summary["score_before"]
    assert summary["objective_after"] < 0.7 * summary["objective_before"]
    assert [len(s.vertices) for s in out] == [18, 18]
    assert summary["objective_after"] == pytest.approx(float(projector.objective(out, data)[0]), rel=1e-9)


def _round_bubbles():
    """Two round bubbles' scan and their coarse fit."""
    truth = [circle_surface([-1.0, 0.2], 0.7, MU, control=64, levels=3), circle_surface([1.0, -0.3], 0.8, MU,
                                                                                        control=64, levels=3)]
    projector, data = _scan([t.fine() for t in truth])
    return projector, data, _coarse_fit(projector, data, ([-1.0, 0.2], [1.0, -0.3]), 0.75)


def test_refit_of_round_bubbles_stops_after_the_trial_and_keeps_the_coarse_ones():
    projector, data, coarse = _round_bubbles()
    out, summary = refine_and_fit(projector, coarse, data, iterations=30, trial=5)
    assert not summary["kept"] and 2 <= summary["iterations"] <= 5  # the trial, or half of it (out_of_reach)
    assert out == coarse


def test_akaike_score_charges_two_per_unknown():
    assert akaike_score(5.0, 100, 10) - akaike_score(5.0, 100, 4) == pytest.approx(12.0)
    assert akaike_score(5.0, 100, 4) == pytest.approx(100 * np.log(0.1) + 8)


def test_a_repair_that_costs_the_refinement_its_advantage_keeps_the_coarse_bubbles():
    from bubsub.clients.pipeline.static.refine import refine_and_check

    centres = ([-1.2, 0.0], [1.1, 0.3])
    projector, data = _scan([_rounded_square(c, 0.9, 0.15) for c in centres])
    coarse = _coarse_fit(projector, data, centres, 0.9)
    summary_of = {"violations_found": [], "actions": [], "violations_remaining": [], "dropped": 0, "repaired": True}

    def harmless(items):
        return list(items), dict(summary_of)

    def drops_one(items):
        return list(items)[:1], dict(summary_of, dropped=1)

    out, summary, validity = refine_and_check(projector, coarse, data, harmless, iterations=30)
    assert summary["kept"] and validity is not None and [len(s.vertices) for s in out] == [18, 18]
    assert summary["score_after_repair"] == pytest.approx(summary["score_after"], abs=1e-6 * abs(summary["score_after"]))
    out, summary, validity = refine_and_check(projector, coarse, data, drops_one, iterations=30)
    assert not summary["kept"] and validity is None and out == coarse
    assert summary["score_after_repair"] > summary["score_before"]


def test_an_unfinished_coarse_fit_does_not_pass_its_own_progress_off_as_the_refinement_s():
    from bubsub.clients.optimise.fit import fit
    from bubsub.clients.pipeline.static.refine import coarse_rate

    truth = [circle_surface([-1.0, 0.2], 0.7, MU, control=64, levels=3), circle_surface([1.0, -0.3], 0.8, MU,
                                                                                        control=64, levels=3)]
    projector, data = _scan([t.fine() for t in truth])
    start = [circle_surface(c, 0.6, MU) for c in ([-0.9, 0.3], [1.1, -0.2])]
    unfinished = fit(projector, start, data, iterations=8, progress=False)
    rate = coarse_rate(unfinished.history)
    assert rate > 0 and coarse_rate(unfinished.history[:5]) == 0.0
    # judged against the coarse objective alone, refining round bubbles looks worth its unknowns ...
    _, naive = refine_and_fit(projector, unfinished.surfaces, data, iterations=30, trial=5)
    assert naive["kept"] and naive["iterations"] > 5
    # ... but not against what the coarse fit would have reached by going on
    out, fair = refine_and_fit(projector, unfinished.surfaces, data, iterations=30, trial=5, coarse_rate=rate)
    assert not fair["kept"] and fair["iterations"] <= 5 and out == unfinished.surfaces


def test_a_trial_stops_once_its_bar_is_out_of_reach_at_its_best_pace():
    from bubsub.clients.pipeline.static.refine import out_of_reach

    # best drop 3: 12 below the bar takes more than 3 x 3 iterations at that pace, 8 does not
    assert out_of_reach([100.0, 97.0, 95.0, 94.0], 82.0, 3)
    assert not out_of_reach([100.0, 97.0, 95.0, 94.0], 86.0, 3)
    assert not out_of_reach([100.0, 97.0], 50.0, 20)  # 20 more iterations of 3 reach it
    assert out_of_reach([100.0, 100.0], 99.0, 5)  # no progress at all
    assert not out_of_reach([100.0, 90.0], 95.0, 0)  # already below the bar


def test_a_hopeless_refinement_stops_at_half_its_trial():
    projector, data, coarse = _round_bubbles()
    out, summary = refine_and_fit(projector, coarse, data, iterations=30, trial=10)
    # round bubbles: the refined fit's best pace cannot pay for four times the unknowns
    assert not summary["kept"] and 5 <= summary["iterations"] < 10
    assert summary["stop_reason"] == TRIAL_FAILED and out == coarse
    assert "callback" not in TRIAL_FAILED


def test_a_repairs_rise_in_the_objective_is_not_passed_off_as_the_refinements_gain():
    from bubsub.clients.pipeline.regions.local import scene_objective
    from bubsub.clients.pipeline.static.repair import shrunk

    projector, data, coarse = _round_bubbles()
    reached = scene_objective(projector, coarse, data)
    # a repair that moved a bubble off the data (as a separation from a neighbour does): any refit regains it
    repaired = [shrunk(coarse[0], 0.9), coarse[1]]
    rise = scene_objective(projector, repaired, data) - reached
    assert rise > 0.5 * reached
    # judged from the repaired objective, refining round bubbles looks worth its unknowns ...
    _, naive = refine_and_fit(projector, repaired, data, iterations=30, trial=5)
    assert naive["kept"] and naive["iterations"] > 5 and naive["objective_reached"] == naive["objective_before"]
    # ... but not from what the coarse bubbles had before the repair
    out, fair = refine_and_fit(projector, repaired, data, iterations=30, trial=5, reached=reached)
    assert fair["objective_reached"] == pytest.approx(fair["objective_before"] - rise, rel=1e-9)
    assert not fair["kept"] and fair["iterations"] <= 5 and out == repaired
