"""bubsub.core.analysis.dynamics: T1 events, growth rates and law, disappearances, sizes over time."""

import numpy as np
import pytest
from scipy.stats import linregress

from bubsub.core.analysis.dynamics import Step, fit_growth_law, growth_rates, size_tables, t1_events, track_events
from bubsub.core.analysis.snapshot import analyse_meshes
from bubsub.core.projection.subdivision import sphere_surface

R, FILM = 0.4, 0.01
S = R + FILM / 2
H = np.sqrt((2 * R + FILM) ** 2 - S ** 2)  # c and d touch both a and b, not each other


def t1_centres(after):
    """Four bubbles a, b, c, d: a-b touch and c, d touch both (before); rotated a quarter turn (after)."""
    if not after:
        return {1: (-S, 0, 0), 2: (S, 0, 0), 3: (0, H, 0), 4: (0, -H, 0)}
    return {1: (-H, 0, 0), 2: (H, 0, 0), 3: (0, S, 0), 4: (0, -S, 0)}


def t1_surfaces(after):
    return {i: sphere_surface(c, R, -0.1, levels=3) for i, c in t1_centres(after).items()}


def step_of(surfaces, index, time, gap=0.03):
    ids = sorted(surfaces)
    snap = analyse_meshes([surfaces[i].fine() for i in ids], ids, contact_gap=gap, grid=(1, 1, 1), shells=1)
    return snap.step(index, time)


def test_a_hand_made_t1_is_found_with_its_four_bubbles():
    before, after = step_of(t1_surfaces(False), 0, 0.0), step_of(t1_surfaces(True), 1, 2.0)
    assert before.pairs == {(1, 2), (1, 3), (1, 4), (2, 3), (2, 4)}
    assert after.pairs == {(3, 4), (1, 3), (1, 4), (2, 3), (2, 4)}
    events = t1_events([after, before])  # in any order: sorted by time
    assert len(events) == 1
    e = events[0]
    assert (e["lost_a"], e["lost_b"], e["gained_c"], e["gained_d"]) == (1, 2, 3, 4)
    assert (e["time_before"], e["time_after"], e["subscan_before"], e["subscan_after"]) == (0.0, 2.0, 0, 1)
    assert [e["x"], e["y"], e["z"]] == pytest.approx([0, 0, 0], abs=1e-9)
    # a and b drift apart while c and d stay apart: a contact lost, none gained, no T1
    apart = t1_surfaces(False)
    apart[1], apart[2] = (sphere_surface((-S - 0.05, 0, 0), R, -0.1, levels=3),
                          sphere_surface((S + 0.05, 0, 0), R, -0.1, levels=3))
    lost_only = step_of(apart, 1, 2.0)
    assert (1, 2) not in lost_only.pairs and (3, 4) not in lost_only.pairs
    assert t1_events([before, lost_only]) == []


def _step(index, time, ids, volumes, coordination=None, pairs=(), centroids=None):
    n = len(ids)
    return Step(index, float(time), np.array(ids), np.array(volumes, dtype=float),
                np.array(coordination if coordination is not None else [0] * n),
                np.array(centroids if centroids is not None else np.zeros((n, 3)), dtype=float), frozenset(pairs))


def test_growth_rates_by_central_differences_and_at_the_ends_of_a_track():
    times = [0.0, 1.0, 3.0]
    steps = [_step(k, t, [7, 8], [1.0 + 0.2 * t, 2.0 if k != 1 else np.nan]) for k, t in enumerate(times)]
    rows = growth_rates(steps)
    seven = [r for r in rows if r["bubble_id"] == 7]
    assert [r["volume_rate"] for r in seven] == pytest.approx([0.2, 0.2, 0.2])  # linear: exact, central or not
    mid = seven[1]
    assert mid["two_thirds_rate"] == pytest.approx((1.6 ** (2 / 3) - 1.0) / 3.0)
    eight = [r for r in rows if r["bubble_id"] == 8]  # its middle volume is unknown (cut by the field of view)
    assert [r["subscan"] for r in eight] == [0, 2] and eight[0]["volume_rate"] == pytest.approx(0.0)
    alone = growth_rates([_step(0, 0.0, [1], [1.0])])
    assert np.isnan(alone[0]["volume_rate"])


def test_growth_law_slope_intercept_and_their_errors_match_least_squares():
    rng = np.random.default_rng(0)
    z = rng.integers(3, 14, size=200).astype(float)
    k, z0 = 2e-3, 8.5
    y = k * (z - z0) + rng.normal(scale=2e-3, size=z.size)
    law = fit_growth_law(z, y)
    ref = linregress(z, y)
    assert law["slope"] == pytest.approx(ref.slope) and law["slope_stderr"] == pytest.approx(ref.stderr)
    assert law["intercept"] == pytest.approx(ref.intercept)
    assert law["intercept_stderr"] == pytest.approx(ref.intercept_stderr)
    assert abs(law["slope"] - k) < 3 * law["slope_stderr"] and abs(law["z0"] - z0) < 3 * law["z0_stderr"]
    # Z0's error by the delta method against the spread of refits on resampled noise
    z0s = [fit_growth_law(z, k * (z - z0) + rng.normal(scale=2e-3, size=z.size))["z0"] for _ in range(300)]
    assert np.std(z0s) == pytest.approx(law["z0_stderr"], rel=0.25)
    flat = fit_growth_law(np.full(5, 6.0), np.arange(5.0))
    assert flat["slope"] is None and "same coordination" in flat["reason"]


def test_coalescence_disappearance_and_appearance():
    s0 = _step(0, 0.0, [1, 2, 3], [1.0, 0.5, 0.2], pairs={(1, 2)}, centroids=[[0, 0, 0], [1, 0, 0], [5, 5, 5]])
    s1 = _step(1, 1.0, [1, 9], [1.48, 0.3])
    events = {e["bubble_id"]: e for e in track_events([s0, s1])}
    assert events[2]["kind"] == "coalescence" and events[2]["partner_id"] == 1 and events[2]["x"] == 1.0
    assert events[3]["kind"] == "disappearance" and events[3]["partner_id"] is None
    assert events[9]["kind"] == "appearance" and events[9]["volume"] == 0.3


def test_size_statistics_and_distribution():
    r = np.array([0.2, 0.3, 0.3, 0.5])
    v = 4 / 3 * np.pi * r ** 3
    steps = [_step(0, 0.0, [1, 2, 3, 4, 5], [*v, np.nan]), _step(1, 1.0, [1, 2], v[:2])]
    sizes, dist = size_tables(steps, bins=[0.1, 0.25, 0.4, 0.6])
    first = sizes[0]
    assert first["bubbles"] == 5 and first["bubbles_whole"] == 4
    assert first["mean_radius"] == pytest.approx(r.mean()) and first["median_radius"] == pytest.approx(0.3)
    assert first["sauter_radius"] == pytest.approx((r ** 3).sum() / (r ** 2).sum())
    assert [d["bubbles"] for d in dist if d["subscan"] == 0] == [1, 2, 1]
    assert [d["fraction"] for d in dist if d["subscan"] == 1] == [0.5, 0.5, 0.0]
