"""Two new bubbles on one cap at the detector's top edge are made one; two caps side by side stay two (3D); the
cold start's bubbles likewise.

The data are projected from icospheres (not the fitted subdivision model) with Gaussian noise of a fixed seed.
"""

import numpy as np
import pytest
import trimesh

from bubsub.core import MeshProjector, ScanGeometry, sphere_surface
from bubsub.core.projection.mesh import Mesh
from bubsub.clients.pipeline.dynamic4d.chain import DynamicSettings
from bubsub.clients.pipeline.dynamic4d.caps import merged_caps, merged_cold_caps, stacked
from bubsub.clients.pipeline.regions.local import scene_residual

CONTRAST = -0.1
GEOMETRY = ScanGeometry.parallel(np.linspace(0, np.pi, 24, endpoint=False), pixel_size=0.05, cols=64, rows=32)
TOP = 0.8  # the top edge plane: 32 rows of 0.05 mm about z = 0
SETTINGS = DynamicSettings(iterations=20, progress=False)


def ball(centre, radius):
    m = trimesh.creation.icosphere(subdivisions=3)
    return Mesh(np.asarray(m.vertices) * radius + np.asarray(centre), np.asarray(m.faces), CONTRAST)


def scan(balls):
    data = MeshProjector(GEOMETRY).forward([ball(*b) for b in balls])
    return (data + np.random.default_rng(5).normal(0, 0.002, data.shape)).astype(np.float32)


def merge(data, warm, pieces):
    """``warm`` (the warm fit's bubbles, ids 1, 2, ...) and ``pieces`` (new, ids 10, 11, ...) through merged_caps."""
    projector = MeshProjector(GEOMETRY)
    ids = list(range(1, len(warm) + 1))
    new = [10 + k for k in range(len(pieces))]
    after = list(warm) + list(pieces)
    residual = scene_residual(projector, after, data)
    lineage = {"new": {i: "at the top edge of the field of view" for i in new}, "coalescences": []}
    out = merged_caps(projector, residual, ids, ids + new, after, lineage, SETTINGS, touch=0.1)
    return projector, residual, out


def test_two_new_pieces_on_one_cap_become_one_bubble():
    cap = ((0.1, 0.0, 0.95), 0.45)  # 0.3 mm (6 rows) of it in view
    below = ((-0.6, 0.3, -0.3), 0.35)
    data = scan([cap, below])
    warm = [sphere_surface(below[0], below[1], CONTRAST, control=42)]
    # a seed on the cap and a piece a split cut out of a neighbour, side by side on it
    pieces = [sphere_surface((-0.1, 0.0, 0.85), 0.25, CONTRAST, control=42),
              sphere_surface((0.3, 0.05, 0.85), 0.25, CONTRAST, control=42)]
    projector, residual, (ids, after, lineage, merged) = merge(data, warm, pieces)
    assert len(merged) == 1 and sorted(ids) == [1, merged[0]["id"]]
    assert merged[0]["with"] not in lineage["new"] and merged[0]["id"] in lineage["new"]
    one = dict(zip(ids, after))[merged[0]["id"]].fine().vertices
    inside = one[one[:, 2] < TOP]
    np.testing.assert_allclose(inside[:, :2].mean(axis=0), cap[0][:2], atol=0.06)
    assert abs(float(inside[:, 2].min()) - 0.5) < 0.06  # the cap's lowest point
    # the residual was kept up to date in place
    fresh = scene_residual(projector, after, data)
    np.testing.assert_allclose(residual, fresh, atol=1e-5)


def test_two_caps_side_by_side_stay_two():
    caps = [((-0.27, 0.0, 0.95), 0.26), ((0.27, 0.0, 0.95), 0.26)]  # a film 0.02 mm thick between them
    data = scan(caps)
    pieces = [sphere_surface(c, r, CONTRAST, control=42) for c, r in caps]
    gap = np.min(np.linalg.norm(pieces[0].fine().vertices[:, None] - pieces[1].fine().vertices[None], axis=2))
    assert gap < 0.1  # they touch: the pair is tried
    _, _, (ids, after, lineage, merged) = merge(data, [], pieces)
    assert merged == [] and ids == [10, 11] and set(lineage["new"]) == {10, 11}


def test_a_warm_fit_bubble_at_the_edge_is_never_merged():
    cap = ((0.1, 0.0, 0.95), 0.45)
    data = scan([cap])
    halves = [sphere_surface((-0.1, 0.0, 0.85), 0.25, CONTRAST, control=42),
              sphere_surface((0.3, 0.05, 0.85), 0.25, CONTRAST, control=42)]
    # one half is the successor's bubble (a track that goes on): no pair of new bubbles to try
    _, _, (ids, after, lineage, merged) = merge(data, halves[:1], halves[1:])
    assert merged == [] and ids == [1, 10]


def test_a_cold_start_cap_taken_twice_becomes_one_and_is_refitted():
    cap = ((0.1, 0.0, 0.95), 0.45)
    below = ((-0.6, 0.3, -0.3), 0.35)
    data = scan([cap, below])
    # the cold start's bubbles: the one below, a large piece of the cap and a small one on its top
    cold = [sphere_surface(below[0], below[1], CONTRAST, control=42),
            sphere_surface((0.05, 0.0, 0.9), 0.38, CONTRAST, control=42),
            sphere_surface((0.35, 0.0, 0.82), 0.12, CONTRAST, control=42)]
    projector = MeshProjector(GEOMETRY)
    after, merged, objective = merged_cold_caps(projector, data, cold, SETTINGS, touch=0.1)
    assert merged == [{"id": 1, "with": 2}] and len(after) == 2 and after[0] is cold[0]
    one = after[1].fine().vertices
    inside = one[one[:, 2] < TOP]
    np.testing.assert_allclose(inside[:, :2].mean(axis=0), cap[0][:2], atol=0.06)
    assert abs(float(inside[:, 2].min()) - 0.5) < 0.06
    assert objective == pytest.approx(0.5 * float(np.sum(scene_residual(projector, after, data) ** 2)), rel=1e-4)
    assert objective < 0.5 * float(np.sum(scene_residual(projector, cold, data) ** 2))


def test_cold_start_caps_side_by_side_are_not_tried_and_a_small_one_above_stays():
    caps = [((-0.27, 0.0, 0.95), 0.26), ((0.27, 0.0, 0.95), 0.26)]
    cold = [sphere_surface(c, r, CONTRAST, control=42) for c, r in caps]
    assert not stacked(*cold) and not stacked(*cold[::-1])
    after, merged, objective = merged_cold_caps(MeshProjector(GEOMETRY), scan(caps), cold, SETTINGS, touch=0.1)
    assert merged == [] and objective is None and after == cold
    # a small bubble above a large one at the top edge, a film of 0.02 mm between them: tried, and kept two
    pair = [((0.0, 0.0, 0.4), 0.45), ((0.38, 0.0, 0.85), 0.12)]
    cold = [sphere_surface(c, r, CONTRAST, control=42) for c, r in pair]
    assert stacked(*cold)
    after, merged, objective = merged_cold_caps(MeshProjector(GEOMETRY), scan(pair), cold, SETTINGS, touch=0.1)
    assert merged == [] and objective is None and after == cold
