"""Warm subscans of reconstruct4d find what their successor lacks: new bubbles, coalescences, tracks that end.

Each scene is one warm subscan whose successor's bubbles (the warm starts) differ from the truth the way a
flowing, coarsening foam makes them differ. The truth is projected from fine polygons and icospheres (not the
fitted subdivision model), with Gaussian noise of a fixed seed.
"""

import numpy as np
import pytest
import trimesh

from bubsub.core import MeshProjector, ScanGeometry, circle_surface, sphere_surface
from bubsub.core.io.scanfile import Scan
from bubsub.core.projection.mesh import Mesh, Polygon
from bubsub.clients.pipeline.dynamic4d.chain import BubbleState, DynamicSettings, SubscanResult, reconstruct_subscan
from bubsub.clients.pipeline.dynamic4d.lineage import lineage_rows

CONTRAST = -0.1


def disc(centre, radius, n=128):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return Polygon(np.c_[centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t)], CONTRAST)


def ball(centre, radius):
    m = trimesh.creation.icosphere(subdivisions=3)
    return Mesh(np.asarray(m.vertices) * radius + np.asarray(centre), np.asarray(m.faces), CONTRAST)


def noisy_scan(geometry, truth, seed):
    data = MeshProjector(geometry).forward(truth)
    data = data + np.random.default_rng(seed).normal(0, 0.002, data.shape)
    return Scan(data=data.astype(np.float32), geometry=geometry, bubble_contrast=CONTRAST)


def by_id(result):
    return dict(zip(result.state.ids, result.state.surfaces()))


# -- 2D: a bubble that vanishes later, two that coalesce later ------------------------------------------------------
TRUTH_2D = {"A": ((-0.46, -0.6), 0.45), "B": ((0.46, -0.6), 0.45),  # touching: one bubble in the successor
            "V": ((0.0, 0.75), 0.3),  # shrinks to nothing before the successor
            "C": ((-1.7, 0.9), 0.4), "D": ((1.7, 0.9), 0.4)}


@pytest.fixture(scope="module")
def scene2d():
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 20, endpoint=False), pixel_size=0.05, cols=100)
    scan = noisy_scan(g, [disc(*x) for x in TRUTH_2D.values()], seed=1)
    merged = circle_surface((0.0, -0.6), 0.45 * np.sqrt(2), CONTRAST)  # the pair's gas as one round bubble
    successor = BubbleState.from_surfaces([10, 11, 12], [merged, circle_surface(*TRUTH_2D["C"], CONTRAST),
                                                         circle_surface(*TRUTH_2D["D"], CONTRAST)], next_id=20)
    res = reconstruct_subscan(scan, successor, DynamicSettings(iterations=20, progress=False), index=4, time=4.5)
    return successor, res


def test_a_bubble_that_vanishes_forward_in_time_is_found_before_it_vanishes(scene2d):
    successor, res = scene2d
    new = {int(i) for i in res.report["new"]}
    (v_id,) = [i for i in new if np.linalg.norm(by_id(res)[i].fine().centroid - TRUTH_2D["V"][0]) < 0.1]
    v = by_id(res)[v_id].fine()
    assert np.sqrt(v.area / np.pi) == pytest.approx(TRUTH_2D["V"][1], rel=0.1)
    assert "inside the field of view" in res.report["new"][str(v_id)]
    for i, key in ((11, "C"), (12, "D")):  # the neighbours keep their ids and their size
        s = by_id(res)[i].fine()
        assert np.sqrt(s.area / np.pi) == pytest.approx(TRUTH_2D[key][1], rel=0.05)


def test_touching_bubbles_that_coalesce_forward_in_time_are_split_backwards(scene2d):
    successor, res = scene2d
    assert 10 not in res.state.ids and "coalescence" in res.report["ended"]["10"]
    (c,) = res.report["coalescences"]
    assert c["parent"] == 10 and len(set(c["children"])) == 2
    found = sorted(np.asarray(by_id(res)[i].fine().centroid)[0] for i in c["children"])
    assert found == pytest.approx([TRUTH_2D["A"][0][0], TRUTH_2D["B"][0][0]], abs=0.05)
    # the lineage in forward time: the two children coalesce into 10 between subscans 4 and 5
    after = SubscanResult(5, 5.5, successor, (), {"start": "cold"})
    rows = lineage_rows([res, after], "s")
    (row,) = [r for r in rows if r["event"] == "coalescence"]
    assert (row["subscan_before"], row["subscan"], row["time_s"]) == (4, 5, 5.5)
    assert row["child_ids"] == "10" and set(row["parent_ids"].split(";")) == {str(i) for i in c["children"]}
    assert not [r for r in rows if r["event"] == "birth"]  # 10's start is the coalescence, not a birth
    ends = {r["parent_ids"] for r in rows if r["event"] == "end"}
    assert ends == set(res.report["new"])


def test_new_ids_are_unique_and_never_reused(scene2d):
    successor, res = scene2d
    ids = list(res.state.ids)
    assert len(ids) == len(set(ids)) == len(TRUTH_2D)
    fresh = set(ids) - set(successor.ids)
    # ids 13..19 ended earlier in the chain (successor.next_id == 20): new bubbles start above them
    assert fresh and min(fresh) >= 20 and res.state.next_id == max(fresh) + 1


# -- 3D: a bubble at the top edge that leaves later, one that leaves through the bottom -----------------------------
@pytest.fixture(scope="module")
def scene3d():
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 16, endpoint=False), pixel_size=0.1, cols=32, rows=24)
    truth = {"A": ((-0.5, 0.0, -0.1), 0.45),
             "T": ((0.5, 0.3, 1.15), 0.4),  # half above the detector's top: gone from view in the successor
             "L": ((0.5, 0.3, -1.8), 0.4)}  # wholly below the bottom: still in view in the successor
    scan = noisy_scan(g, [ball(*x) for x in truth.values()], seed=2)
    successor = BubbleState.from_surfaces([0, 1], [sphere_surface((-0.5, 0.0, 0.0), 0.45, CONTRAST),
                                                   sphere_surface((0.5, 0.3, -1.1), 0.4, CONTRAST)])
    res = reconstruct_subscan(scan, successor, DynamicSettings(iterations=20, progress=False), index=2, time=2.0)
    return truth, successor, res


def test_a_bubble_entering_through_the_top_edge_gets_a_new_id(scene3d):
    truth, successor, res = scene3d
    assert res.report["new"] and set(res.state.ids) == {0, int(next(iter(res.report["new"])))}
    (new,) = [int(i) for i in res.report["new"]]
    assert new >= 2 and "top edge" in res.report["new"][str(new)]
    c = np.asarray(by_id(res)[new].fine().centroid)
    assert c[:2] == pytest.approx(truth["T"][0][:2], abs=0.05)


def test_a_bubble_leaving_through_the_bottom_ends_its_track(scene3d):
    truth, successor, res = scene3d
    assert res.ended == (1,) and "left the field of view" in res.report["ended"]["1"] and "bottom" in res.report["ended"]["1"]
    rows = lineage_rows([res, SubscanResult(3, 3.0, successor, (), {"start": "cold"})], "s")
    (birth,) = [r for r in rows if r["event"] == "birth"]
    assert (birth["child_ids"], birth["subscan"]) == ("1", 3)
    a = by_id(res)[0].fine()
    assert a.equivalent_radius == pytest.approx(truth["A"][1], rel=0.05)


def test_analysis_takes_coalescences_and_appearances_from_the_lineage():
    from bubsub.core.analysis.dynamics import Step, track_events

    def step(index, ids, volumes, centres):
        return Step(index, float(index), np.array(ids), np.array(volumes, float), np.zeros(len(ids), int),
                    np.array(centres, float), frozenset())

    # 3 and 4 coalesce into 7 (no contact recorded, so the volumes alone call them disappearances); 5 is born
    s0 = step(0, [1, 3, 4], [1.0, 0.2, 0.3], [[0, 0, 0], [1, 0, 0], [1.5, 0, 0]])
    s1 = step(1, [1, 7, 5], [1.0, 0.5, 0.1], [[0, 0, 0], [1.2, 0, 0], [0, 2, 0]])
    guessed = {(r["kind"], r["bubble_id"]) for r in track_events([s0, s1])}
    assert guessed == {("disappearance", 3), ("disappearance", 4), ("appearance", 7), ("appearance", 5)}
    lineage = [{"event": "coalescence", "subscan_before": "0", "subscan": "1", "parent_ids": "3;4", "child_ids": "7"},
               {"event": "birth", "subscan_before": "0", "subscan": "1", "parent_ids": "", "child_ids": "5"}]
    rows = track_events([s0, s1], lineage)
    assert {(r["kind"], r["bubble_id"], r["partner_id"]) for r in rows} == {
        ("coalescence", 3, 7), ("coalescence", 4, 7), ("appearance", 5, None)}


def test_ids_of_new_bubbles_stay_unique_across_chunks():
    """Each chunk numbers its new bubbles from its own cold start; the linker gives them fresh ids."""
    from bubsub.clients.cluster.chunks import run_chunks

    def scripted(scan, previous, settings, index=0, time=0.0):
        if previous is None:  # the same two bubbles wherever a chunk starts cold
            state = BubbleState.from_surfaces([0, 1], [circle_surface((0, 0), 1, CONTRAST),
                                                       circle_surface((3, 0), 1, CONTRAST)])
            return SubscanResult(index, time, state, (), {"start": "cold", "ended": {}})
        new = previous.next_id  # one bubble found anew per warm subscan, at a place of its own
        items = previous.surfaces() + [circle_surface((10.0 * index, 5), 1, CONTRAST)]
        state = BubbleState.from_surfaces([*previous.ids, new], items, next_id=new + 1)
        return SubscanResult(index, time, state, (), {"start": "warm", "ended": {}, "new": {str(new): "inside"},
                                                      "coalescences": []})

    results, interrupted, links = run_chunks(None, lambda k: None, [3, 2, 1, 0], DynamicSettings(progress=False),
                                             step=scripted, chunks=2)
    assert not interrupted and sorted(r.index for r in results) == [0, 1, 2, 3]
    states = {r.index: r for r in results}
    # chunk 0 (subscans 3, 2, 1) found ids 2 and 3; chunk 1's own id 2 (found at subscan 0) must not reuse them
    assert states[1].state.ids == (0, 1, 2, 3)
    assert states[0].state.ids == (0, 1, 4) and set(states[0].report["new"]) == {"4"}
    places = {}
    for r in results:  # one id, one bubble: every id keeps its place through the subscans it has
        for i, s in zip(r.state.ids, r.state.surfaces()):
            places.setdefault(i, set()).add(tuple(np.round(s.vertices.mean(axis=0), 6)))
    assert all(len(p) == 1 for p in places.values()) and len({next(iter(p)) for p in places.values()}) == 5


def test_a_bubble_cut_by_the_top_edge_keeps_its_track_as_it_comes_into_view():
    """Going backwards a bubble that leaves through the top later comes down into view: its warm start is not
    shrunk toward its centroid above the edge (that would carry its visible cap out of view)."""
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 16, endpoint=False), pixel_size=0.1, cols=32, rows=24)
    truth = [((-0.5, 0.0, -0.1), 0.45), ((0.5, 0.3, 1.38), 0.4)]  # the top edge is at z = 1.2
    scan = noisy_scan(g, [ball(*x) for x in truth], seed=3)
    successor = BubbleState.from_surfaces([0, 1], [sphere_surface(truth[0][0], 0.45, CONTRAST),
                                                   sphere_surface((0.5, 0.3, 1.48), 0.4, CONTRAST)])
    res = reconstruct_subscan(scan, successor, DynamicSettings(iterations=20, progress=False), index=2, time=2.0)
    assert res.state.ids == (0, 1) and res.report["new"] == {} and res.ended == ()
    c = np.asarray(by_id(res)[1].fine().centroid)
    assert c[:2] == pytest.approx(truth[1][0][:2], abs=0.05)
