"""The simulated foam column: analytic chords against the mesh projector and closed forms, packing, folder."""

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from bubsub.core import MeshProjector, ScanGeometry
from bubsub.core.foam.checks import unit_icosphere
from bubsub.core.foam.column import column_geometry, column_phantom, simulate_column
from bubsub.core.foam.ellipsoids import (contact_function, cylinder_chords, ellipsoid_chords, ellipsoid_mesh,
                                         ellipsoid_volumes, project_cylinder, project_ellipsoids, shape_matrices)

SMALL = dict(rows=48, cols=144, pixel_size=0.012)  # field of view 1.728 mm wide, 0.576 mm high


@pytest.fixture(scope="module")
def small():
    return column_phantom(40, seed=3, **SMALL)


def _geometry():
    return ScanGeometry.parallel(np.linspace(0, np.pi, 8, endpoint=False), pixel_size=0.02, cols=80, rows=60)


def test_ellipsoid_projection_matches_mesh_projector_and_ray_formula():
    g = _geometry()
    c, a = np.array([0.13, -0.07, 0.05]), np.array([0.45, 0.32, 0.22])
    rot = Rotation.from_euler("xyz", [0.4, 1.1, -0.7]).as_matrix()
    p = project_ellipsoids(g, c[None], a[None], rot[None], -0.1, supersampling=2)
    origins, directions = g.rays(2)
    rays = -0.1 * ellipsoid_chords(origins, directions, c, a, rot).mean(axis=-1)
    np.testing.assert_allclose(p, rays, rtol=0, atol=1e-12)
    mesh = MeshProjector(g, supersampling=2).forward([ellipsoid_mesh(c, a, rot, -0.1, subdivisions=5)])
    assert np.abs(mesh - p).sum() / np.abs(p).sum() < 2e-4
    assert np.abs(mesh - p).max() < 2e-3 * np.abs(p).max()
    # every view's line integrals times the pixel area add up to attenuation x volume
    np.testing.assert_allclose(p.sum(axis=(1, 2)) * 0.02**2, -0.1 * ellipsoid_volumes(a[None])[0], rtol=5e-4)


def test_cylinder_chords_closed_form():
    s = np.linspace(-1.2, 1.2, 25)
    o = np.stack([s, np.full_like(s, -5.0), np.zeros_like(s)], axis=1)
    np.testing.assert_allclose(cylinder_chords(o, [0.0, 1.0, 0.0], 1.0, (-1, 1)),
                               2 * np.sqrt(np.clip(1 - s**2, 0, None)), atol=1e-7)
    # oblique ray through both caps, vertical rays inside and outside, a ray above the cylinder
    o = np.array([[0, 0, 0.5], [0.3, 0.2, 7.0], [1.5, 0, 0.0], [0, -3, 2.0]])
    d = np.array([[1, 0, 1], [0, 0, -1], [0, 0, 1], [0, 1, 0]], dtype=float)
    np.testing.assert_allclose(cylinder_chords(o, d, 1.0, (0.0, 1.0)), [np.sqrt(2), 1.0, 0.0, 0.0], atol=1e-12)
    g = _geometry()
    p = project_cylinder(g, 0.7, (-5, 5), 0.1, supersampling=1)
    col = (np.arange(80) - 40 + 0.5) * 0.02
    want = 0.1 * 2 * np.sqrt(np.clip(0.7**2 - col**2, 0, None))
    np.testing.assert_allclose(p, np.broadcast_to(want, p.shape), atol=1e-12)


def test_contact_function_of_spheres_and_scaling():
    # two spheres of radii 1 and 2: F = (|r| / 3)^2, touching at |r| = 3
    s1, s2 = np.eye(3)[None], 4 * np.eye(3)[None]
    r = np.array([[3.0, 0, 0], [1.5, 0, 0], [0, 0, 6.0]])
    np.testing.assert_allclose(contact_function(np.repeat(s1, 3, 0), np.repeat(s2, 3, 0), r), [1, 0.25, 4],
                               rtol=1e-7)


def _surface_points(ph, b, subdivisions=3):
    u, _ = unit_icosphere(subdivisions)
    return ph.centres[b] + (u * ph.axes[b]) @ ph.rotations[b].T


def test_bubbles_disjoint_with_a_film_and_inside_the_column(small):
    ph = small
    tree = cKDTree(ph.centres)
    reach = 2 * ph.axes.max() + ph.gap
    grown = shape_matrices(ph.axes + 0.99 * ph.gap, ph.rotations, -2)  # points >= gap away lie outside
    pairs = tree.query_pairs(reach, output_type="ndarray")
    assert len(pairs) > 20
    for i, j in pairs:
        for a, b in ((i, j), (j, i)):
            q = _surface_points(ph, a) - ph.centres[b]
            assert np.einsum("ni,ij,nj->n", q, grown[b], q).min() > 1.0, (a, b)
    for b in range(len(ph.centres)):
        assert np.hypot(*_surface_points(ph, b)[:, :2].T).max() <= ph.radius - 0.99 * ph.gap


def test_gas_fraction_and_bubble_count_near_the_targets():
    ph = column_phantom(300, seed=1, **SMALL)
    assert abs(int(ph.visible.sum()) - 300) < 45
    assert abs(ph.gas_fraction - 0.4) < 0.04
    # independent estimate: random points in the liquid within the rows, inside any ellipsoid
    rng = np.random.default_rng(0)
    n = 200_000
    rho, th = ph.radius * np.sqrt(rng.uniform(size=n)), rng.uniform(0, 2 * np.pi, n)
    pts = np.stack([rho * np.cos(th), rho * np.sin(th), rng.uniform(-1, 1, n) * ph.fov_half_height], axis=1)
    m = shape_matrices(ph.axes, ph.rotations, -2)
    inside = np.zeros(n, bool)
    for b, near in enumerate(cKDTree(pts).query_ball_point(ph.centres, ph.axes.max(axis=1))):
        q = pts[near] - ph.centres[b]
        inside[np.asarray(near, int)[np.einsum("ni,ij,nj->n", q, m[b], q) <= 1]] = True
    assert abs(inside.mean() - ph.gas_fraction) < 0.006


def test_seeds_reproducible(small):
    again = column_phantom(40, seed=3, **SMALL)
    np.testing.assert_array_equal(again.centres, small.centres)
    np.testing.assert_array_equal(again.rotations, small.rotations)
    other = column_phantom(40, seed=4, **SMALL)
    assert other.centres.shape != small.centres.shape or not np.allclose(other.centres, small.centres)
    a, b = simulate_column(small, n_angles=6), simulate_column(again, n_angles=6)
    np.testing.assert_array_equal(a.data, b.data)


def test_cut_bubbles_at_top_and_bottom(small):
    top, bottom = small.cut()
    vis = small.visible
    assert (top & vis).sum() >= 2 and (bottom & vis).sum() >= 2
    h = small.fov_half_height
    meshes = dict(zip(np.flatnonzero(vis), small.truth_meshes(subdivisions=3)))
    for b in np.flatnonzero(top):
        z = meshes[b].vertices[:, 2]
        assert z.min() < h < z.max()
    for b in np.flatnonzero(bottom):
        z = meshes[b].vertices[:, 2]
        assert z.min() < -h < z.max()
    frac = small.fraction_in_fov()
    assert np.all((frac[top | bottom] > 0) & (frac[top | bottom] < 1))
    assert np.all(frac[vis & ~top & ~bottom] == 1)


def test_scan_noise_and_background(small):
    noisy = simulate_column(small, n_angles=10, photons=1e4)
    clean = simulate_column(small, n_angles=10, photons=None)
    np.testing.assert_array_equal(noisy.background, clean.background)
    # Poisson counts at I0 exp(-p): the line-integral error has variance exp(p) / I0
    z = (noisy.data.astype(float) - clean.data) * np.sqrt(1e4 * np.exp(-clean.data.astype(float)))
    assert abs(z.mean()) < 0.03 and abs(z.std() - 1) < 0.03
    bubbles = clean.bubble_data
    assert bubbles.max() <= 1e-6 and bubbles.min() < -0.01  # gas is darker than the liquid everywhere


def test_simulation_folder_is_read_by_reconstruct_and_evaluate(tmp_path):
    from bubsub.clients.cli.main import main
    from bubsub.clients.pipeline.evaluation.evaluate import evaluate_dir
    from bubsub.core.io.meshio import read_ply, write_ply
    from bubsub.core.io.scanfile import read_scan

    out = tmp_path / "sim"
    assert main(["simulate", "--phantom", "column", "--bubbles", "40", "--det-count", "96", "--angles", "8",
                 "--out", str(out)]) == 0
    scan = read_scan(out / "scan.h5")
    assert scan.data.shape == (8, 32, 96) and scan.geometry.kind == "parallel3d_vec"
    meta = json.loads((out / "phantom.json").read_text())
    truth = read_ply(out / meta["truth"])
    assert len(truth) == meta["bubbles"] == scan.attrs["n_bubbles"]
    assert meta["column"]["bubbles_cut_top"] > 0 and meta["column"]["bubbles_cut_bottom"] > 0
    rec = tmp_path / "rec"
    rec.mkdir()
    write_ply(rec / "bubbles.ply", truth[1:])
    res = evaluate_dir(rec, out)
    assert res["bubbles_truth"] == len(truth) and 0 < res["ddi"] < 0.5
    write_ply(rec / "bubbles.ply", truth)
    assert evaluate_dir(rec, out)["ddi"] == 0.0
    assert main(["simulate", "--phantom", "column", "--beam", "cone", "--out", str(tmp_path / "x")]) != 0
    assert not (tmp_path / "x").exists()


def test_truth_meshes_rasterise_like_the_ellipsoids(small):
    from bubsub.core.foam.column import truth_grid
    from bubsub.core.foam.ellipsoids import ellipsoid_labels
    from bubsub.core.metrics import dice_dissimilarity, label_image

    shape, extent = truth_grid(small, voxel=small.pixel_size)
    vis = np.flatnonzero(small.visible)
    meshes = label_image(small.truth_meshes(subdivisions=4), shape, extent)
    exact = ellipsoid_labels(small.centres[vis], small.axes[vis], small.rotations[vis], shape, extent)
    missing = sorted(set(range(1, len(vis) + 1)) - set(np.unique(exact)))
    assert np.all(small.fraction_in_fov()[vis[np.array(missing, int) - 1]] < 0.05)  # only slivers hold no voxel
    assert dice_dissimilarity(meshes > 0, exact > 0) < 1e-3
    assert np.mean(meshes[exact > 0] == exact[exact > 0]) > 0.998


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="gas_fraction"):
        column_phantom(100, gas_fraction=0.7, **SMALL)
    with pytest.raises(ValueError, match="radius_fraction"):
        column_phantom(100, radius_fraction=1.2, **SMALL)
    with pytest.raises(ValueError, match="too few"):
        column_phantom(1, **SMALL)
    with pytest.raises(ValueError, match="parallel-beam"):
        g = ScanGeometry.cone(np.zeros(2), source_origin=10, origin_detector=10, cols=8, rows=8)
        project_ellipsoids(g, np.zeros((1, 3)), np.ones((1, 3)), np.eye(3)[None], 1.0)
    assert column_geometry(column_phantom(40, seed=3, **SMALL), 5).shape == (5, 48, 144)
