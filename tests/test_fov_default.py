"""The field-of-view model as the default: a bubble cut by the detector's top measured against its analytic
cap, a liquid wider than the detector accepted, ``bubsub evaluate`` scoring inside the field of view."""

import json

import numpy as np
import pytest

from bubsub.core.foam.containers import sphere_mesh
from bubsub.core.foam.ellipsoids import project_ellipsoids
from bubsub.core.io.meshio import write_ply
from bubsub.core.io.scanfile import Scan
from bubsub.core.metrics import shapes_dice_dissimilarity
from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.projection.mesh import Mesh
from bubsub.clients.cli.main import build_parser
from bubsub.clients.pipeline.inputs.sides import check_lateral_truncation
from bubsub.clients.pipeline.evaluation.evaluate import evaluate_dir
from bubsub.clients.pipeline.inputs.fov import field_of_view, size_inside_fov
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, reconstruct

C = -0.1


def _cap(r, h):
    """Volume of a ball's cap of height ``h`` (mm^3)."""
    return np.pi * h * h * (3 * r - h) / 3


def test_the_model_is_the_default_and_a_flag_switches_it_off_also_in_4d(tmp_path):
    from bubsub.clients.pipeline.dynamic4d.chain import DynamicSettings, _static_settings

    assert ReconstructionSettings().fov_model is True
    scan = tmp_path / "s.h5"
    scan.write_bytes(b"")

    def parse(*extra):
        return build_parser().parse_args(["reconstruct", str(scan), "--out", str(tmp_path / "o"), *extra])

    assert parse().fov_model is True and parse("--fov-model").fov_model is True
    assert parse("--no-fov-model").fov_model is False
    assert _static_settings(DynamicSettings()).fov_model is True  # the 4D cold start and its warm starts


def test_a_bubble_cut_by_the_detectors_top_is_measured_within_two_percent_of_its_visible_cap():
    # 24 parallel views of a 40 x 16 detector: field of view radius 1 mm, half height 0.4 mm; the ball's top
    # 0.18 mm above the detector, projected exactly (closed-form chords), no noise
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 24, endpoint=False), pixel_size=0.05, cols=40, rows=16)
    r_xy, half_z = field_of_view(g)
    centre, r = np.array([0.12, -0.05, 0.26]), 0.32
    data = project_ellipsoids(g, centre[None], np.full((1, 3), r), np.eye(3)[None], C, supersampling=2)
    rec = reconstruct(Scan(data=data.astype(np.float32), geometry=g, bubble_contrast=C),
                      ReconstructionSettings(progress=False))
    assert len(rec.surfaces) == 1, rec.report["bubbles"]
    visible = 4 / 3 * np.pi * r ** 3 - _cap(r, centre[2] + r - half_z)
    assert size_inside_fov(rec.surfaces[0].fine(), (r_xy, half_z)) == pytest.approx(visible, rel=0.02)
    assert rec.report["unobserved_control_vertices"][0] > 0  # the cap above the detector is not measured
    # 6 pixels in radius: one Loop level, not the two of --levels (and no refinement takes it from a 3D bubble)
    assert rec.report["subdivision_levels"] == {"1": 1}


def _column_scan(radius_over_fov):
    """A liquid cylinder with two bubbles, 12 parallel views of a 48 x 12 detector (field of view radius
    1.2 mm), the cylinder's projection as background (exact chords)."""
    from bubsub.core.foam.ellipsoids import project_cylinder

    g = ScanGeometry.parallel(np.linspace(0, np.pi, 12, endpoint=False), pixel_size=0.05, cols=48, rows=12)
    radius = radius_over_fov * field_of_view(g)[0]
    background = project_cylinder(g, radius, (-1.0, 1.0), 0.1, 2)
    data = project_ellipsoids(g, np.array([[0.3, 0.1, 0.0], [-0.4, -0.2, 0.05]]), np.full((2, 3), 0.25),
                              np.stack([np.eye(3)] * 2), C, supersampling=2, out=background.copy())
    noise = np.random.default_rng(0).normal(0, 0.002, data.shape)
    return Scan(data=(data + noise).astype(np.float32), geometry=g, background=background.astype(np.float32),
                bubble_contrast=C)


def test_a_liquid_wider_than_the_detector_held_by_the_background_is_not_truncation():
    # the bubbles inside the field of view; the liquid inside it or wider, its projection the background
    for radius_over_fov in (0.9, 1.03, 1.5):
        assert check_lateral_truncation(_column_scan(radius_over_fov)) is None
    # without a background the liquid's edge is not in the data: the bubbles' signal is checked instead
    scan = _column_scan(0.9)
    scan.data = scan.bubble_data.copy()
    scan.background = None
    assert check_lateral_truncation(scan) is None


def test_evaluate_scores_only_the_truth_grids_voxels_inside_the_field_of_view(tmp_path):
    half_z = 0.4
    truth = sphere_mesh((0.0, 0.0, 0.3), 0.3, C, subdivisions=3)  # its top 0.2 mm above the field of view
    v = np.asarray(truth.vertices).copy()
    v[:, 2] = np.minimum(v[:, 2], half_z)  # the same bubble, flattened where the data do not see it
    rec = Mesh(v, truth.faces, C)
    shape, extent = (40, 32, 32), (-0.4, 0.4, -0.4, 0.4, -0.2, 0.8)
    sim, out = tmp_path / "sim", tmp_path / "rec"
    sim.mkdir(), out.mkdir()
    write_ply(sim / "truth.ply", [truth])
    (sim / "phantom.json").write_text(json.dumps({"ndim": 3, "truth": "truth.ply", "grid_shape": list(shape),
                                                  "grid_extent": list(extent)}))
    write_ply(out / "bubbles.ply", [rec])
    (out / "report.json").write_text(json.dumps({"dimension": 3, "field_of_view_mm": {
        "radius": 2.0, "half_height": half_z, "margin": 0.05}}))
    res = evaluate_dir(out, sim)
    whole = shapes_dice_dissimilarity([rec], [truth], shape, extent)
    assert res["ddi"] < 0.01 < 0.05 < whole  # the cap above the detector no longer counts
    assert res["scored_on"].endswith("inside the field of view")
    (out / "report.json").write_text(json.dumps({"dimension": 3}))
    assert evaluate_dir(out, sim)["ddi"] == pytest.approx(whole)  # no field of view known: the whole grid


@pytest.mark.parametrize("factor", [0.3, 2.0])
def test_an_unseen_cap_that_collapsed_or_swelled_is_continued_as_the_sphere_the_seen_part_lies_on(factor):
    from bubsub.core import sphere_surface
    from bubsub.clients.pipeline.static.repair import continued

    centre, r = np.array([0.1, -0.2, 0.3]), 0.4
    ball = sphere_surface(centre, r, C)
    v = ball.vertices.copy()
    unseen = v[:, 2] > centre[2] + 0.5 * r  # the cap above the detector's top (its control vertices)
    v[unseen] = centre + factor * (v[unseen] - centre)  # folded in, or standing off
    out = continued(ball.with_vertices(v), unseen)
    assert np.array_equal(out.vertices[~unseen], v[~unseen])  # what the data see is kept
    fine = out.fine().vertices
    dist = np.linalg.norm(fine - centre, axis=1)
    truth = np.linalg.norm(ball.fine().vertices - centre, axis=1)
    assert np.abs(dist - truth).max() < 0.02 * r  # the subdivided sphere again, to 2 % of its radius
    assert abs(out.fine().volume - ball.fine().volume) < 0.01 * ball.fine().volume
    few = v[:, 2] > centre[2] - 0.8 * r  # under a quarter seen: the sphere it started as is left alone
    assert np.array_equal(continued(ball.with_vertices(v), few).vertices, v)


def test_a_cap_thinner_than_the_previews_voxels_is_seeded_from_the_detectors_edge_row():
    from bubsub.core import MeshProjector
    from bubsub.clients.pipeline.static.initial import choose_initial, edge_slices
    from bubsub.clients.pipeline.static.preview import voxel_preview

    # 20 parallel views of a 64 x 24 detector of 25 um pixels: field of view radius 0.8 mm, half height 0.3 mm
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 20, endpoint=False), pixel_size=0.025, cols=64, rows=24)
    half_z = field_of_view(g)[1]
    r, lift = 0.2, 0.16  # the second ball's centre 0.16 mm above the top: a cap 0.04 mm high, 0.12 mm across
    centres = np.array([[-0.2, -0.1, 0.0], [0.3, 0.2, half_z + lift]])
    data = project_ellipsoids(g, centres, np.full((2, 3), r), np.stack([np.eye(3)] * 2), C, supersampling=2)
    ((lo, down, _, _), (top, up, discs, radii)) = edge_slices(data, g, C, (-0.8, 0.8, -0.8, 0.8), 0.025)
    assert (lo, down, top, up) == pytest.approx((-half_z, -1.0, half_z, 1.0))
    k = np.argmin(np.linalg.norm(discs - centres[1, :2], axis=1))
    assert np.linalg.norm(discs[k] - centres[1, :2]) < 0.03
    assert radii[k] == pytest.approx(np.sqrt(r * r - lift * lift), abs=0.04)
    # a preview of 50 um voxels (two rows each): the cap is half a voxel high
    image, extent = voxel_preview(data, g, C, 0.05)
    proj = MeshProjector(g)

    def seeds(model):
        surfaces, _ = choose_initial(image, extent, C, proj, data, detector="dt", estimate=False,
                                     border_is_background=not model)
        return np.array([s.control.vertices.mean(axis=0) for s in surfaces])

    near = lambda c: np.linalg.norm(c[:, :2] - centres[1, :2], axis=1) < 0.05
    assert not near(seeds(False)).any()
    found = seeds(True)
    assert near(found).sum() == 1 and found[near(found)][0, 2] > half_z  # centred beyond the edge plane
    assert len(found) == 2


def test_topology_never_merges_a_bubble_that_reaches_the_edge_of_the_field_of_view():
    from bubsub.core import MeshProjector, sphere_surface
    from bubsub.clients.pipeline.static.topology import adapt_topology

    g = ScanGeometry.parallel(np.linspace(0, np.pi, 16, endpoint=False), pixel_size=0.05, cols=40, rows=16)
    # one ball of 0.3 mm started as two halves side by side: inside the field of view (z = 0) the merge wins;
    # at z = 0.3 the ball crosses the detector's top (0.4 mm) and the pair is left alone
    for z, merged in ((0.0, True), (0.3, False)):
        data = project_ellipsoids(g, np.array([[0.0, 0.0, z]]), np.full((1, 3), 0.3), np.eye(3)[None], C,
                                  supersampling=2)
        start = [sphere_surface((-0.15, 0, z), 0.16, C), sphere_surface((0.15, 0, z), 0.16, C)]
        out, summary = adapt_topology(MeshProjector(g), start, data, preview=None,
                                      new_bubble=lambda c, r: sphere_surface(c, r, C), min_radius=0.05,
                                      max_radius=0.5, rounds=1, steps=("merge",), touch=0.05, fov_edge=True)
        assert len(out) == (1 if merged else 2)
        if not merged:  # the same pair without the rule: merged
            out, _ = adapt_topology(MeshProjector(g), start, data, preview=None,
                                    new_bubble=lambda c, r: sphere_surface(c, r, C), min_radius=0.05,
                                    max_radius=0.5, rounds=1, steps=("merge",), touch=0.05)
            assert len(out) == 1


def test_prune_drops_a_sliver_at_the_detectors_edge_by_the_part_the_data_see():
    from bubsub.core.projection.subdivision import sphere_surface
    from bubsub.clients.pipeline.reconstruct import prune, seen_slab

    g = ScanGeometry.parallel(np.linspace(0, np.pi, 20, endpoint=False), pixel_size=0.025, cols=64, rows=24)
    half_z = field_of_view(g)[1]
    assert seen_slab(g) == (np.inf, pytest.approx(half_z))
    assert seen_slab(ScanGeometry.parallel(np.linspace(0, np.pi, 20), cols=64)) is None  # 2D: seen whole
    r = 0.2
    seen = lambda h: _cap(r, h)  # a cap h high below the top plane
    sliver = sphere_surface([0.0, 0.0, half_z + r - 0.03], r, C, levels=3)  # 0.03 mm of it seen
    cap = sphere_surface([0.3, 0.0, half_z + r - 0.1], r, C, levels=3)  # 0.1 mm seen
    inside = sphere_surface([-0.3, 0.0, 0.0], 0.07, C, levels=3)  # whole, small
    r_sliver = (3 * seen(0.03) / (4 * np.pi)) ** (1 / 3)  # 0.05 mm: the radius of a ball of what is seen
    r_cap = (3 * seen(0.1) / (4 * np.pi)) ** (1 / 3)
    assert r_sliver < 0.06 < r_cap
    kept, dropped = prune([sliver, cap, inside], 0.06, fov=seen_slab(g))
    assert dropped == 1 and kept[0] is cap and kept[1] is inside
    # whole bubbles are judged whole, as before
    assert prune([sliver, cap, inside], 0.06)[1] == 0
    assert prune([sliver, cap, inside], 0.045, fov=seen_slab(g))[1] == 0
