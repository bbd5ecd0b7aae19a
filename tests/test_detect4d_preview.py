"""A warm subscan's data preview splits the bubbles that hold two of its bubble centres (3D).

Each scene is one warm subscan of ``reconstruct4d``: the truth is projected from icospheres (not the fitted
subdivision model) with Gaussian noise of a fixed seed; the warm fit's bubbles are what a backward chain hands
on from the successor.
"""

import numpy as np
import pytest
import trimesh

from bubsub.core import MeshProjector, ScanGeometry, SubdivisionSurface, sphere_surface
from bubsub.core.io.scanfile import Scan
from bubsub.core.projection.mesh import Mesh
from bubsub.clients.pipeline.dynamic4d.detect import detect_warm
from bubsub.clients.pipeline.dynamic4d.chain import BubbleState, DynamicSettings, SubscanResult, reconstruct_subscan
from bubsub.clients.pipeline.dynamic4d.lineage import lineage_rows
from bubsub.clients.optimise.fit import fit
from bubsub.clients.pipeline.regions.local import Footprints, scene_residual
from bubsub.clients.pipeline.static.topology import MERGE_CONVEXITY, convexity, split_step

CONTRAST = -0.1
GEOMETRY = ScanGeometry.parallel(np.linspace(0, np.pi, 24, endpoint=False), pixel_size=0.05, cols=64, rows=32)


def ball(centre, radius):
    m = trimesh.creation.icosphere(subdivisions=3)
    return Mesh(np.asarray(m.vertices) * radius + np.asarray(centre), np.asarray(m.faces), CONTRAST)


def noisy_data(truth, seed):
    data = MeshProjector(GEOMETRY).forward([ball(*x) for x in truth.values()])
    return (data + np.random.default_rng(seed).normal(0, 0.002, data.shape)).astype(np.float32)


def nearest(surfaces, point):
    d = [np.linalg.norm(np.asarray(s.fine().centroid) - point) for s in surfaces]
    return int(np.argmin(d)), float(min(d))


def test_touching_bubbles_that_coalesce_forward_in_time_are_split_backwards_with_the_lineage():
    truth = {"A": ((-0.42, 0.1, 0.0), 0.4), "B": ((0.42, 0.1, 0.0), 0.4), "C": ((0.2, -1.0, 0.1), 0.3)}
    scan = Scan(data=noisy_data(truth, seed=5), geometry=GEOMETRY, bubble_contrast=CONTRAST)
    joint = 0.4 * 2 ** (1 / 3)  # the successor: the pair's gas as one round bubble
    successor = BubbleState.from_surfaces([10, 11], [sphere_surface((0.0, 0.1, 0.0), joint, CONTRAST),
                                                     sphere_surface(truth["C"][0], 0.3, CONTRAST)], next_id=20)
    res = reconstruct_subscan(scan, successor, DynamicSettings(iterations=20, progress=False), index=4, time=4.5)
    ids = list(res.state.ids)
    assert len(ids) == len(set(ids)) == 3 and 11 in ids and 10 not in ids
    assert "coalescence" in res.report["ended"]["10"]
    (c,) = res.report["coalescences"]
    assert c["parent"] == 10 and len(set(c["children"])) == 2 and min(c["children"]) >= 20
    surfaces = dict(zip(ids, res.state.surfaces()))
    for key in ("A", "B"):
        i, d = nearest([surfaces[j] for j in c["children"]], truth[key][0])
        assert d < 0.06
        r = surfaces[c["children"][i]].fine().equivalent_radius
        assert r == pytest.approx(truth[key][1], rel=0.1)
    rows = lineage_rows([res, SubscanResult(5, 5.5, successor, (), {"start": "cold"})], "s")
    (row,) = [r for r in rows if r["event"] == "coalescence"]
    assert row["child_ids"] == "10" and set(row["parent_ids"].split(";")) == {str(i) for i in c["children"]}


def test_a_neighbour_swollen_into_a_vanished_bubbles_space_is_split_and_keeps_its_id():
    """Its fitted shape is too round for the elongation test (axis ratio 1.4 < 1.6): only the preview's two
    centres inside it call for the split."""
    truth = {"N": ((-0.3, 0.0, 0.0), 0.45), "V": ((0.47, 0.05, 0.0), 0.3), "F": ((0.0, -1.1, 0.0), 0.35)}
    data = noisy_data(truth, seed=6)
    unit = sphere_surface((0.0, 0.0, 0.0), 1.0, CONTRAST, control=42)
    swollen = SubdivisionSurface(Mesh(unit.vertices * [0.7, 0.5, 0.5] + [-0.05, 0.02, 0.0], unit.control_faces,
                                      CONTRAST), unit.levels)
    fitted = [swollen, sphere_surface(truth["F"][0], 0.35, CONTRAST, control=42)]
    size_n = 4 / 3 * np.pi * 0.45 ** 3  # N in the successor; V had vanished there
    ids, after, lineage, summary, next_id = detect_warm(
        GEOMETRY, data, [3, 4], fitted, DynamicSettings(iterations=20, progress=False),
        successor_sizes={3: size_n, 4: 4 / 3 * np.pi * 0.35 ** 3}, next_id=9)
    assert len(ids) == len(set(ids)) == 3 and summary["changes"].get("preview_split") == 1
    k, d = nearest(after, truth["N"][0])
    assert ids[k] == 3 and d < 0.06 and after[k].fine().equivalent_radius == pytest.approx(0.45, rel=0.1)
    k, d = nearest(after, truth["V"][0])
    assert ids[k] == 9 and next_id == 10 and d < 0.06
    assert after[k].fine().equivalent_radius == pytest.approx(0.3, rel=0.15)
    assert "split off bubble 3" in lineage["new"][9] and not lineage["coalescences"]



def _split_of_one_fitted_to(truth, blobs, seed, neck_convexity):
    """split_step on one bubble fitted to ``truth``'s data with ``blobs`` (centres, radii) as the preview's
    centres in it, and an unknowns cost no split can pay: only the neck rule can split.

    Returns (convexity of the one bubble, whether it was split)."""
    data = noisy_data(truth, seed)
    projector = MeshProjector(GEOMETRY)
    size = sum(4 / 3 * np.pi * r ** 3 for _, r in truth.values())
    centre = np.mean([c for c, _ in truth.values()], axis=0)
    one = fit(projector, [sphere_surface(centre, (3 * size / (4 * np.pi)) ** (1 / 3), CONTRAST)], data,
              iterations=40, progress=False).surfaces
    residual, own, changes = scene_residual(projector, one, data), Footprints(projector, one), []
    out, _ = split_step(projector, one, residual, own, data, lambda c, r: sphere_surface(c, r, CONTRAST), changes,
                        0, ratio=np.inf, iterations=15, max_tries=1, cost=1e9, blobs=blobs,
                        neck_convexity=neck_convexity)
    return convexity(one[0]), len(out) == 2


def test_one_bubble_with_a_neck_over_a_pair_about_to_coalesce_is_split_without_the_unknowns_cost():
    """Two balls a thin film apart (they coalesce in the successor): the one bubble fitted to them keeps their
    neck, and two bubbles fit at least as well: split by the neck rule even where the objective's drop alone
    would not pay the second bubble's unknowns; not without the rule, and never a convex bubble."""
    pair = {"A": ((-0.41, 0.05, 0.0), 0.4), "B": ((0.41, 0.05, 0.0), 0.4)}
    blobs = (np.array([c for c, _ in pair.values()]), np.array([0.4, 0.4]))
    neck, split = _split_of_one_fitted_to(pair, blobs, 7, MERGE_CONVEXITY)
    assert neck < MERGE_CONVEXITY and split
    assert not _split_of_one_fitted_to(pair, blobs, 7, 0.0)[1]
    lone = {"A": ((0.0, 0.05, 0.0), 0.4 * 2 ** (1 / 3))}
    blobs = (np.array([[-0.25, 0.05, 0.0], [0.25, 0.05, 0.0]]), np.array([0.25, 0.25]))
    round_one, split = _split_of_one_fitted_to(lone, blobs, 7, MERGE_CONVEXITY)
    assert round_one > MERGE_CONVEXITY and not split
