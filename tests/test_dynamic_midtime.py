"""Events during a subscan, read at its mid-time: a coalescence is split backwards only when the pair was still
two bubbles then, and a bubble that vanished before it is not found there.

The truth is projected from fine polygons, view by view as the foam was when each view was taken: the two touching
discs before the film breaks, one ellipse of their area and second moments after it; a disc, then nothing.
"""

import numpy as np
import pytest

from bubsub.core import MeshProjector, ScanGeometry, circle_surface
from bubsub.core.io.scanfile import Scan
from bubsub.core.projection.mesh import Polygon
from bubsub.clients.pipeline.dynamic4d.chain import BubbleState, DynamicSettings, reconstruct_subscan
from bubsub.clients.pipeline.dynamic4d.midtime import MIDTIME_DROP, midtime_drop, spans_a_period
from bubsub.clients.pipeline.regions.local import scene_objective

CONTRAST = -0.1
VIEWS = 20
PAIR = (((-0.46, -0.6), 0.45), ((0.46, -0.6), 0.45))
OTHERS = (((-1.7, 0.9), 0.4), ((1.7, 0.9), 0.4))


def ellipse(centre, a, b, n=128):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return Polygon(np.c_[centre[0] + a * np.cos(t), centre[1] + b * np.sin(t)], CONTRAST)


def merged_pair():
    """The ellipse with the pair's area and second moments (the flowing phantom's coalescence)."""
    (c0, r), (c1, _) = PAIR
    a, b = 2 * np.sqrt(r ** 2 / 4 + ((c1[0] - c0[0]) / 2) ** 2), r
    scale = np.sqrt(2 * r ** 2 / (a * b))
    return ellipse(((c0[0] + c1[0]) / 2, c0[1]), a * scale, b * scale)


def coalescing_scan(breaks_at, seed=2):
    """A subscan whose pair's film breaks before view ``breaks_at`` (acquisition order)."""
    g = ScanGeometry.parallel(np.linspace(0, np.pi, VIEWS, endpoint=False), pixel_size=0.05, cols=100)
    others = [ellipse(c, r, r) for c, r in OTHERS]
    two = MeshProjector(g).forward([ellipse(c, r, r) for c, r in PAIR] + others)
    one = MeshProjector(g).forward([merged_pair()] + others)
    data = np.concatenate([two[:breaks_at], one[breaks_at:]])
    data = data + np.random.default_rng(seed).normal(0, 0.002, data.shape)
    return Scan(data=data.astype(np.float32), geometry=g, bubble_contrast=CONTRAST)


def run(breaks_at):
    merged = circle_surface((0.0, -0.6), 0.45 * np.sqrt(2), CONTRAST)
    successor = BubbleState.from_surfaces([10, 11, 12], [merged] + [circle_surface(c, r, CONTRAST) for c, r in OTHERS],
                                          next_id=20)
    return reconstruct_subscan(coalescing_scan(breaks_at), successor, DynamicSettings(iterations=20, progress=False),
                               index=4, time=4.5)


VANISHING = ((0.0, 0.75), 0.3)


def vanishing_run(gone_at, seed=3):
    """A subscan in which a disc the successor lacks is seen by the views before ``gone_at`` only."""
    g = ScanGeometry.parallel(np.linspace(0, np.pi, VIEWS, endpoint=False), pixel_size=0.05, cols=100)
    rest = [ellipse(c, r, r) for c, r in PAIR + OTHERS]
    with_it = MeshProjector(g).forward(rest + [ellipse(*VANISHING, VANISHING[1])])
    data = np.concatenate([with_it[:gone_at], MeshProjector(g).forward(rest)[gone_at:]])
    data = data + np.random.default_rng(seed).normal(0, 0.002, data.shape)
    scan = Scan(data=data.astype(np.float32), geometry=g, bubble_contrast=CONTRAST)
    successor = BubbleState.from_surfaces([10, 11, 12, 13], [circle_surface(c, r, CONTRAST) for c, r in PAIR + OTHERS],
                                          next_id=20)
    return reconstruct_subscan(scan, successor, DynamicSettings(iterations=20, progress=False), index=4, time=4.5)


def near_vanishing(res):
    return [i for i, s in zip(res.state.ids, res.state.surfaces())
            if np.linalg.norm(np.asarray(s.fine().centroid) - VANISHING[0]) < 0.15]


def test_a_film_broken_early_in_the_subscan_leaves_one_bubble_there():
    res = run(breaks_at=4)  # 20 % of the way through: one bubble at mid-time
    assert not res.report["coalescences"] and 10 in res.state.ids
    assert res.report["detection"]["changes"].get("coalescence_before_midtime") == 1
    bubble = dict(zip(res.state.ids, res.state.surfaces()))[10].fine()
    assert abs(bubble.area) == pytest.approx(2 * np.pi * 0.45 ** 2, rel=0.1)
    assert np.asarray(bubble.centroid) == pytest.approx([0.0, -0.6], abs=0.05)
    # the residual the undo kept up to date is the scene's: the reported objective is the result's own
    scan = coalescing_scan(4)
    own = scene_objective(MeshProjector(scan.geometry), res.state.surfaces(), scan.bubble_data)
    assert res.report["objective"] == pytest.approx(own, rel=1e-4)


def test_a_film_broken_late_in_the_subscan_is_a_coalescence_after_it():
    res = run(breaks_at=16)  # 80 % of the way through: two bubbles at mid-time
    (c,) = res.report["coalescences"]
    assert c["parent"] == 10 and 10 not in res.state.ids
    assert "coalescence_before_midtime" not in res.report["detection"]["changes"]
    xs = sorted(np.asarray(dict(zip(res.state.ids, res.state.surfaces()))[i].fine().centroid)[0]
                for i in c["children"])
    assert xs == pytest.approx([PAIR[0][0][0], PAIR[1][0][0]], abs=0.08)


def test_the_drop_measures_the_jump_across_the_period_against_the_view_to_view_change():
    theta = np.linspace(0, np.pi, 40, endpoint=False)
    periodic = 1.0 + 0.5 * np.cos(2 * theta)  # a foam that does not change: the gain joins up across the ends
    assert abs(midtime_drop(periodic)) < 1.5
    stepped = periodic + np.where(np.arange(40) < 10, 2.0, 0.0)  # two bubbles for the first quarter only
    assert midtime_drop(stepped) > MIDTIME_DROP
    assert midtime_drop(periodic - np.where(np.arange(40) >= 30, 2.0, 0.0)) > MIDTIME_DROP
    assert midtime_drop(periodic + np.where(np.arange(40) >= 30, 2.0, 0.0)) < -MIDTIME_DROP
    assert midtime_drop(np.zeros(40)) == 0.0


def test_only_a_subscan_over_a_full_period_is_read_in_time():
    half = ScanGeometry.parallel(np.linspace(0, np.pi, 40, endpoint=False), pixel_size=0.05, cols=50)
    assert spans_a_period(half)
    assert spans_a_period(ScanGeometry.parallel(np.linspace(3 * np.pi, 4 * np.pi, 40, endpoint=False),
                                                pixel_size=0.05, cols=50))  # continuous rotation: any start
    assert not spans_a_period(ScanGeometry.parallel(np.linspace(0, np.pi / 2, 20, endpoint=False),
                                                    pixel_size=0.05, cols=50))
    cone = dict(source_origin=50.0, origin_detector=10.0, pixel_size=0.05, cols=50)
    assert spans_a_period(ScanGeometry.cone(np.linspace(0, 2 * np.pi, 40, endpoint=False), **cone))
    assert not spans_a_period(ScanGeometry.cone(np.linspace(0, np.pi, 40, endpoint=False), **cone))


def test_a_bubble_gone_before_mid_time_is_not_found_there():
    res = vanishing_run(gone_at=7)  # seen by the first 35 % of the views
    assert near_vanishing(res) == [] and not res.report["new"]
    assert res.report["detection"]["changes"].get("absent_at_midtime") == 1
    assert sorted(res.state.ids) == [10, 11, 12, 13]


def test_a_bubble_gone_after_mid_time_is_found_there():
    res = vanishing_run(gone_at=14)  # seen by the first 70 % of the views
    (i,) = near_vanishing(res)
    assert str(i) in res.report["new"] and "absent_at_midtime" not in res.report["detection"]["changes"]
