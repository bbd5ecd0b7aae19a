"""The field-of-view model: what the data see, cut bubbles seeded and fitted on their visible part only,
their measured part reported (against the exact projector and analytic caps and lenses)."""

import csv
import json

import numpy as np
import pytest

from bubsub.core import MeshProjector, sphere_surface
from bubsub.core.foam.containers import sphere_mesh
from bubsub.core.metrics import bubble_mask, dice_dissimilarity
from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.projection.masks import coverage, pixel_centres
from bubsub.core.projection.mesh import Mesh, Polygon, volume_in_slab
from bubsub.clients.optimise.fit import fit
from bubsub.clients.pipeline.inputs.fov import (field_of_view, fov_mask, seen_by, size_inside_fov, unobserved_control)
from bubsub.clients.pipeline.static.initial import initial_surfaces
from bubsub.clients.pipeline.results.outputs import write_outputs
from bubsub.clients.pipeline.static.preview import voxel_preview
from bubsub.clients.pipeline.reconstruct import Reconstruction

C = -0.1


def _parallel(angles=12, cols=40, rows=16, pixel=0.05):
    return ScanGeometry.parallel(np.linspace(0, np.pi, angles, endpoint=False), pixel_size=pixel, cols=cols,
                                 rows=rows)


def _cone(angles=12):
    return ScanGeometry.cone(np.linspace(0, 2 * np.pi, angles, endpoint=False), source_origin=10.0,
                             origin_detector=10.0, pixel_size=0.1, cols=40, rows=16)


@pytest.mark.parametrize("make", [_parallel, _cone])
def test_seen_by_counts_the_projections_where_the_exact_projector_sees_a_point(make):
    g = make()
    r_xy, half_z = field_of_view(g)
    points = np.array([[0, 0, 0], [0.3, -0.2, 0.5 * half_z], [0, 0, half_z + 0.15], [0, 0, -half_z - 0.15],
                       [1.3 * r_xy, 0, 0], [0.9 * r_xy, 0.9 * r_xy, 0.1], [0.5, 0.4, -0.6 * half_z]])
    counts = seen_by(points, g)
    proj = MeshProjector(g)
    for p, n in zip(points, counts):
        # a ball wider than a pixel, so that some ray's centre crosses it wherever it lands on the detector
        data = proj.forward([sphere_mesh(p, 0.06, 1.0, subdivisions=1)])
        truth = int(np.count_nonzero(data.reshape(g.n_angles, -1).max(axis=1) > 0))
        assert abs(n - truth) <= 1, (p, n, truth)  # one angle may graze the edge with the ball, not its centre
    assert counts[0] == g.n_angles and counts[2] == 0 and 0 < counts[4] < g.n_angles


def test_size_inside_fov_of_spheres_cut_by_the_detector_edge_is_the_cap_volume():
    r, half_z = 0.5, 1.2
    for z in (1.0, 1.2, -1.05):
        m = sphere_mesh((0.3, 0.1, z), r, C, subdivisions=4)
        h = abs(z) + r - half_z  # height of the cap beyond the plane
        ideal = 4 / 3 * np.pi * r ** 3
        cap = np.pi * h * h * (3 * r - h) / 3
        want = m.volume * (1 - cap / ideal)  # the icosphere's volume, scaled as the ideal sphere's
        assert size_inside_fov(m, (2.4, half_z)) == pytest.approx(want, rel=3e-3)
    inside = sphere_mesh((0, 0, 0), r, C, subdivisions=3)
    assert size_inside_fov(inside, (2.4, half_z)) == pytest.approx(inside.volume, rel=3e-3)


def test_volume_in_slab_clips_a_mesh_by_both_planes_as_the_grid_and_the_analytic_segment_do():
    # a ball cut by both planes: the spherical segment between them (the fine icosphere within 1e-3 of the
    # ideal ball), and a tilted ellipsoid against the rasterised coverage of the same mesh (independent route)
    r, z0 = 0.6, 0.1
    ball = sphere_mesh((0.2, -0.1, z0), r, C, subdivisions=5)
    lo, hi = -0.3, 0.45

    def below(h):  # volume of the ideal ball below z = h
        d = np.clip(h - z0 + r, 0, 2 * r)
        return np.pi * d * d * (3 * r - d) / 3

    assert volume_in_slab(ball.vertices, ball.faces, lo, hi) == pytest.approx(below(hi) - below(lo), rel=1e-3)
    assert volume_in_slab(ball.vertices, ball.faces, -5, 5) == pytest.approx(ball.volume, rel=1e-12)
    assert volume_in_slab(ball.vertices, ball.faces, 2, 3) == 0.0
    a = np.diag([0.9, 0.4, 0.3])
    q, _ = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))
    unit = sphere_mesh((0, 0, 0), 1.0, C, subdivisions=4)
    ell = Mesh(unit.vertices @ (q @ a).T + [0.1, 0.0, 0.05], unit.faces, C)
    grid = coverage(ell, (120, 120, 120), (-1.0, 1.2, -1.1, 1.1, -1.1, 1.1), supersample=2)
    zc = pixel_centres((120, 120, 120), (-1.0, 1.2, -1.1, 1.1, -1.1, 1.1))[0]
    h = 2.2 / 120
    lo, hi = -1.1 + 50 * h, -1.1 + 74 * h  # on voxel faces
    raster = float(grid[(zc > lo) & (zc < hi)].sum() * h ** 3)
    assert volume_in_slab(ell.vertices, ell.faces, lo, hi) == pytest.approx(raster, rel=2e-3)
    with pytest.raises(ValueError, match="lies above"):
        volume_in_slab(ball.vertices, ball.faces, 1.0, 0.0)


def test_size_inside_fov_of_a_disc_cut_by_the_field_of_view_circle_is_the_lens_area():
    R, r, d = 2.0, 0.5, 1.8  # field of view radius, disc radius, centre distance
    t = np.linspace(0, 2 * np.pi, 2000, endpoint=False)
    disc = Polygon(np.c_[d + r * np.cos(t), r * np.sin(t)], C)
    lens = (r * r * np.arccos((d * d + r * r - R * R) / (2 * d * r)) + R * R * np.arccos((d * d + R * R - r * r)
            / (2 * d * R)) - 0.5 * np.sqrt((-d + r + R) * (d + r - R) * (d - r + R) * (d + r + R)))
    assert size_inside_fov(disc, (R, 0.0)) == pytest.approx(lens, rel=5e-3)


def test_a_cut_bubble_is_seeded_at_its_visible_cross_section_not_shrunk_inside():
    # a ball of radius 0.5 mm centred on the grid's top face (the detector's top edge)
    shape, extent = (20, 40, 40), (-1.0, 1.0, -1.0, 1.0, -1.0, 0.0)
    z, y, x = np.meshgrid(*[np.linspace(lo + 0.025, hi - 0.025, n) for lo, hi, n in
                            ((-1.0, 0.0, 20), (1.0, -1.0, 40), (-1.0, 1.0, 40))], indexing="ij")
    image = np.where(x ** 2 + y ** 2 + z ** 2 <= 0.5 ** 2, abs(C), 0.0)
    (cut,) = initial_surfaces(image, extent, C, border_is_background=False)
    (shrunk,) = initial_surfaces(image, extent, C, border_is_background=True)
    centre = lambda s: s.control.vertices.mean(axis=0)
    radius = lambda s: np.linalg.norm(s.control.vertices - centre(s), axis=1).mean()
    assert centre(cut)[2] > -0.15 and radius(cut) == pytest.approx(0.5, abs=0.08)
    assert centre(shrunk)[2] < -0.15 and radius(shrunk) < 0.35  # what the grid edge as background gives


def test_extended_preview_seeds_a_bubble_partly_outside_the_reconstructable_disc():
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 60, endpoint=False), pixel_size=0.02, cols=100)
    r_fov = field_of_view(g)[0]
    t = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    truth = [(np.array([0.2, 0.1]), 0.25), (np.array([r_fov, 0.0]), 0.22)]  # the second: half outside
    data = MeshProjector(g).forward([Polygon(c + r * np.c_[np.cos(t), np.sin(t)], C) for c, r in truth])
    image, extent = voxel_preview(data, g, C, 0.03, extend=1.25)
    seeds = initial_surfaces(image, extent, C, border_is_background=False)
    centres = np.array([s.control.vertices.mean(axis=0) for s in seeds])
    for c, r in truth:
        assert np.min(np.linalg.norm(centres - c, axis=1)) < 0.3 * r, (c, centres)


def test_unobserved_control_vertices_stay_put_and_the_visible_part_fits():
    g = _parallel(angles=20, cols=40, rows=16)  # field of view: radius 1 mm, half height 0.4 mm
    fov = field_of_view(g)
    truth = sphere_mesh((0.1, 0.0, 0.3), 0.33, C, subdivisions=4)  # its top 0.23 mm above the detector
    data = MeshProjector(g).forward([truth])
    start = sphere_surface((0.1, 0.0, 0.3), 0.25, C)
    frozen = unobserved_control(start, g)
    assert 0 < frozen.sum() < len(frozen) // 2
    res = fit(MeshProjector(g), [start], data, iterations=25, progress=False)
    end = res.surfaces[0]
    assert np.array_equal(end.vertices[frozen], start.vertices[frozen])
    assert np.all(np.linalg.norm(end.vertices[~frozen] - start.vertices[~frozen], axis=1).max() > 0.02)
    shape, extent = (40, 60, 60), (-0.75, 0.75, -0.75, 0.75, -0.6, 0.4)
    keep = fov_mask(shape, extent, fov)
    ddi = lambda s: dice_dissimilarity(bubble_mask([s.fine()], shape, extent)[keep],
                                       bubble_mask([truth], shape, extent)[keep])
    assert ddi(end) < 0.03 < ddi(start)


def test_bubbles_csv_leaves_a_truncated_bubbles_whole_size_empty_and_reports_its_measured_part(tmp_path):
    half_z = 1.2
    whole = sphere_surface((0, 0, 0), 0.4, C)
    cut = sphere_surface((0.5, 0.5, 1.1), 0.4, C)
    report = {"dimension": 3, "field_of_view_mm": {"radius": 2.4, "half_height": half_z, "margin": 0.05},
              "unobserved_control_vertices": [0, 7]}
    write_outputs(tmp_path, Reconstruction([whole, cut], report))
    rows = list(csv.DictReader(open(tmp_path / "bubbles.csv")))
    assert [r["truncated"] for r in rows] == ["0", "1"]
    assert float(rows[0]["volume_in_fov_mm3"]) == pytest.approx(float(rows[0]["volume_mm3"]))
    assert rows[1]["volume_mm3"] == rows[1]["equivalent_diameter_mm"] == rows[1]["surface_area_mm2"] == ""
    fine = cut.fine()
    # the cap above z = 1.2 of the refined surface, by counting voxels finely (an independent rasterisation)
    shape, extent = (80, 80, 80), (0.05, 0.95, 0.05, 0.95, 0.65, 1.55)
    voxel = 0.9 / 80
    below = fov_mask(shape, extent, (2.4, half_z))
    want = bubble_mask([fine], shape, extent)[below].sum() * voxel ** 3
    assert float(rows[1]["volume_in_fov_mm3"]) == pytest.approx(want, rel=0.02)
    assert [r["unobserved_control_vertices"] for r in rows] == ["0", "7"]
    meta = json.loads((tmp_path / "bubbles.csv-metadata.json").read_text())
    names = [c["name"] for c in meta["tableSchema"]["columns"]]
    assert names[-3:] == ["truncated", "volume_in_fov_mm3", "unobserved_control_vertices"]
