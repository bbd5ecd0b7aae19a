"""Phantoms and rasterisation: compared with areas/volumes, matplotlib and trimesh."""

import time

import numpy as np
import pytest
import trimesh
from matplotlib.path import Path as MplPath

from bubsub.core.projection.mesh import Mesh, Polygon
from bubsub.core.foam.containers import liquid_box, liquid_square, sphere_mesh
from bubsub.core.foam.phantoms import BENCHMARK_SEED, FoamPhantom, foam2d, foam3d, foam3d_benchmark
from bubsub.core.projection.masks import bubble_mask, check_grid, coverage, label_image, pixel_centres, rasterize


def regular_polygon(centre, radius, n=256, attenuation=1.0):
    t = 2 * np.pi * np.arange(n) / n
    return Polygon(np.c_[centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t)], attenuation)


def cube(lo, hi, attenuation=1.0):
    """Axis-aligned box mesh from corner lo to corner hi."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    size = hi - lo
    box = liquid_box(size, attenuation)
    return Mesh(box.vertices + (lo + hi) / 2, box.faces, attenuation)


# -- grids -----------------------------------------------------------------------------------
def test_pixel_centres_follow_the_image_convention():
    y, x = pixel_centres((4, 2), (0.0, 2.0, -2.0, 2.0))
    assert np.allclose(x, [0.5, 1.5])
    assert np.allclose(y, [1.5, 0.5, -0.5, -1.5])  # row 0 at y max
    z, y3, x3 = pixel_centres((2, 4, 2), (0.0, 2.0, -2.0, 2.0, 10.0, 12.0))
    assert np.allclose(z, [10.5, 11.5]) and np.allclose(y3, y)


@pytest.mark.parametrize(
    "shape, extent, word",
    [
        ((10,), (0, 1, 0, 1), "2 or 3 entries"),
        ((10, 0), (0, 1, 0, 1), "positive integers"),
        ((10, 10), (0, 1, 0), "(xmin, xmax, ymin, ymax)"),
        ((10, 10), (0, 1, 1, 1), "empty y range"),
        ((10, 10), (0, np.nan, 0, 1), "finite"),
    ],
)
def test_bad_grids_are_rejected(shape, extent, word):
    with pytest.raises(ValueError, match="grid") as exc:
        check_grid(shape, extent)
    assert word in str(exc.value)


# -- 2D rasterisation ------------------------------------------------------------------------
def test_rasterised_disk_area_matches_pi_r2():
    r = 1.3
    disk = regular_polygon((0.37, -0.21), r, n=1024)
    shape, ext = (800, 800), (-2.0, 2.0, -2.0, 2.0)
    px = 4.0 / 800
    area_centre = bubble_mask([disk], shape, ext).sum() * px * px
    area_super = rasterize([disk], shape, ext, supersample=4).sum() * px * px
    exact = np.pi * r * r
    assert abs(area_centre - exact) < 2 * np.pi * r * px * 0.2  # well below one pixel ring
    assert abs(area_super - exact) < 2e-4 * exact
    assert abs(area_super - exact) < abs(disk.area - exact) + 1e-4  # polygon vs circle


def test_polygon_mask_matches_matplotlib_on_a_nonconvex_star():
    rng = np.random.default_rng(3)
    t = np.sort(rng.uniform(0, 2 * np.pi, 40))
    rad = rng.uniform(0.4, 1.5, t.size)
    star = Polygon(np.c_[0.1 + rad * np.cos(t), -0.2 + rad * np.sin(t)])
    shape, ext = (300, 280), (-1.6, 1.7, -1.9, 1.6)
    y, x = pixel_centres(shape, ext)
    X, Y = np.meshgrid(x, y)
    ref = MplPath(star.vertices).contains_points(np.c_[X.ravel(), Y.ravel()]).reshape(shape)
    got = bubble_mask(star, shape, ext)
    assert got.sum() > 1000
    assert np.array_equal(got, ref)


def test_shared_edges_through_pixel_centres_are_counted_exactly_once():
    # Squares whose corners sit exactly on pixel centres: half-open rules must tile.
    shape, ext = (20, 20), (0.0, 20.0, 0.0, 20.0)  # centres at k + 0.5
    a = Polygon([[2.5, 2.5], [8.5, 2.5], [8.5, 8.5], [2.5, 8.5]])
    b = Polygon([[8.5, 2.5], [14.5, 2.5], [14.5, 8.5], [8.5, 8.5]])
    lab = label_image([a, b], shape, ext)
    assert (lab == 1).sum() == 36 and (lab == 2).sum() == 36
    both = rasterize([a, b], shape, ext)
    assert both.max() == 1.0  # nowhere counted twice
    union = bubble_mask([Polygon([[2.5, 2.5], [14.5, 2.5], [14.5, 8.5], [2.5, 8.5]])], shape, ext)
    assert np.array_equal(union, lab > 0)  # no gap along the shared edge


def test_coverage_of_a_pixel_aligned_square_is_exact_with_supersampling():
    shape, ext = (10, 10), (0.0, 10.0, 0.0, 10.0)
    sq = Polygon([[2.0, 3.0], [5.5, 3.0], [5.5, 7.0], [2.0, 7.0]])  # 3.5 x 4 mm
    cov = coverage(sq, shape, ext, supersample=2)
    assert cov.sum() == pytest.approx(14.0)
    assert set(np.unique(cov)) == {0.0, 0.5, 1.0}


def test_rasterize_rejects_mixed_dimensions_and_bad_supersample():
    sq = liquid_square(2.0)
    with pytest.raises(ValueError, match="3D grid takes Mesh"):
        rasterize([sq], (4, 4, 4), (-1, 1, -1, 1, -1, 1))
    with pytest.raises(ValueError, match="supersample"):
        rasterize([sq], (4, 4), (-1, 1, -1, 1), supersample=0)


# -- 3D rasterisation --------------------------------------------------------------------------
def test_mesh_voxelisation_matches_trimesh_contains():
    sph = sphere_mesh((0.31, -0.17, 0.05), 1.1, -0.1, subdivisions=2)
    shape, ext = (40, 44, 48), (-1.5, 1.9, -1.6, 1.5, -1.2, 1.3)
    got = bubble_mask([sph], shape, ext)
    z, y, x = pixel_centres(shape, ext)
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    ref = trimesh.Trimesh(sph.vertices, sph.faces, process=False).contains(np.c_[X.ravel(), Y.ravel(), Z.ravel()])
    assert got.sum() > 10000
    assert np.count_nonzero(got.ravel() != ref) <= 2  # at most a grazing centre or two


def test_mesh_voxel_volume_matches_mesh_volume():
    sph = sphere_mesh((0.0, 0.0, 0.0), 2.0, 1.0, subdivisions=3)
    shape, ext = (100, 100, 100), (-2.5, 2.5, -2.5, 2.5, -2.5, 2.5)
    vox = 0.05**3
    assert rasterize(sph, shape, ext).sum() * vox == pytest.approx(sph.volume, rel=3e-3)
    assert rasterize(sph, shape, ext, supersample=2).sum() * vox == pytest.approx(sph.volume, rel=1e-3)


def test_cubes_with_corners_on_voxel_centres_tile_exactly():
    # triangle diagonals and vertices pass exactly through voxel centres here
    shape, ext = (12, 12, 12), (0.0, 12.0, 0.0, 12.0, 0.0, 12.0)
    a = cube((1.5, 1.5, 1.5), (5.5, 5.5, 5.5))
    b = cube((5.5, 1.5, 1.5), (9.5, 5.5, 5.5))
    c = cube((1.5, 5.5, 1.5), (5.5, 9.5, 5.5))
    lab = label_image([a, b, c], shape, ext)
    assert [(lab == i).sum() for i in (1, 2, 3)] == [64, 64, 64]
    assert rasterize([a, b, c], shape, ext).max() == 1.0


def test_3d_grid_orientation_y_decreases_with_row_z_increases_with_slice():
    sph = sphere_mesh((0.0, 1.0, -1.0), 0.3, 1.0)
    shape, ext = (20, 20, 20), (-2.0, 2.0, -2.0, 2.0, -2.0, 2.0)
    vol = bubble_mask(sph, shape, ext)
    k, j, i = np.argwhere(vol).mean(axis=0)
    z, y, x = pixel_centres(shape, ext)
    assert np.interp(k, np.arange(20), z) == pytest.approx(-1.0, abs=0.05)
    assert np.interp(j, np.arange(20), y) == pytest.approx(1.0, abs=0.05)
    assert y[int(round(j))] > 0  # the upper half of the image holds y > 0


def test_benchmark_voxelisation_200x200x100_is_fast():
    scene = foam3d_benchmark()
    t0 = time.perf_counter()
    lab = scene.labels((100, 200, 200))
    elapsed = time.perf_counter() - t0
    assert elapsed < 10.0
    assert lab.max() == 100
    vox = 0.1**3
    vols = np.bincount(lab.ravel(), minlength=101)[1:] * vox
    true = np.array([b.volume for b in scene.bubbles])
    assert np.allclose(vols, true, rtol=0.08)
    assert vols.sum() == pytest.approx(true.sum(), rel=0.01)


# -- 2D foam -----------------------------------------------------------------------------------
def pairwise_clearance(centres, bound):
    d = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    np.fill_diagonal(d, np.inf)
    return (d - bound[:, None] - bound[None, :]).min()


def test_foam2d_is_reproducible_and_seed_dependent():
    a, b, c = foam2d(7, n_bubbles=20), foam2d(7, n_bubbles=20), foam2d(8, n_bubbles=20)
    assert all(np.array_equal(p.vertices, q.vertices) for p, q in zip(a.bubbles, b.bubbles))
    assert not np.allclose(a.centres, c.centres)


def test_foam2d_bubbles_are_disjoint_perturbed_and_inside_the_square():
    ph = foam2d(1)
    assert isinstance(ph, FoamPhantom) and ph.ndim == 2
    assert len(ph.bubbles) == 40
    assert ph.contrast == pytest.approx(-0.1)
    assert ph.liquid.attenuation == pytest.approx(0.1)
    assert all(b.attenuation == pytest.approx(-0.1) for b in ph.bubbles)
    assert all(len(b.vertices) == 128 and b.area > 0 for b in ph.bubbles)
    assert np.all((ph.radii >= 0.3) & (ph.radii <= 0.8))
    dev = []
    bound = []
    for b, c, r in zip(ph.bubbles, ph.centres, ph.radii):
        rr = np.linalg.norm(b.vertices - c, axis=1)
        dev.append(np.abs(rr / r - 1).max())
        bound.append(rr.max())
        assert np.all(np.abs(b.vertices) <= 5.0 - 0.25 + 1e-9)
    dev = np.array(dev)
    assert np.all(dev <= 0.03 + 1e-12) and np.all(dev >= 0.015 - 1e-12)  # non-circular, a few %
    assert pairwise_clearance(ph.centres, np.array(bound)) >= 0.05 - 1e-9
    assert 0.3 < ph.gas_fraction < 0.6


def test_foam2d_images_and_labels():
    ph = foam2d(2, n_bubbles=15)
    img = ph.attenuation_image(500)
    assert img.shape == (500, 500)
    assert set(np.unique(img)) <= {0.0, 0.1}
    lab = ph.labels(500)
    assert lab.max() == 15 and lab.dtype == np.int32
    assert np.array_equal(ph.mask(500), lab > 0)
    assert np.array_equal(img == 0.0, lab > 0)  # gas exactly where the labels are
    # pixel counts follow the polygon areas
    areas = np.bincount(lab.ravel())[1:] * (10 / 500) ** 2
    assert np.allclose(areas, [b.area for b in ph.bubbles], rtol=0.05)
    sup = ph.attenuation_image(250, supersample=3)
    assert sup.mean() == pytest.approx(0.1 * (1 - ph.gas_fraction), rel=2e-3)


def test_foam2d_dense_packing_reaches_higher_gas_fraction():
    ph = foam2d(3, n_bubbles=50, packing="dense")
    bound = np.array([np.linalg.norm(b.vertices - c, axis=1).max() for b, c in zip(ph.bubbles, ph.centres)])
    assert pairwise_clearance(ph.centres, bound) >= 0.05 - 1e-9
    assert ph.gas_fraction > 0.48


@pytest.mark.parametrize(
    "kwargs, word",
    [
        (dict(seed=-1), "seed"),
        (dict(seed=1.5), "seed"),
        (dict(seed=0, n_bubbles=0), "n_bubbles"),
        (dict(seed=0, radius_range=(0.8, 0.3)), "radius_range"),
        (dict(seed=0, perturbation=0.7), "perturbation"),
        (dict(seed=0, radius_range=(6.0, 6.0)), "does not fit"),
        (dict(seed=0, n_bubbles=400), "could not place"),
        (dict(seed=0, packing="tight"), "packing"),
    ],
)
def test_foam2d_bad_input(kwargs, word):
    with pytest.raises(ValueError, match=word):
        foam2d(**kwargs)


# -- 3D foam -------------------------------------------------------------------------------------
def test_liquid_box_and_square():
    box = liquid_box((20, 20, 10), 0.1)
    assert len(box.faces) == 12 and box.volume == pytest.approx(4000.0)
    assert np.allclose(box.vertices.min(axis=0), [-10, -10, -5])
    sq = liquid_square(10.0, 0.1)
    assert sq.area == pytest.approx(100.0)


def test_foam3d_benchmark_is_the_fixed_scene():
    a, b = foam3d_benchmark(), foam3d_benchmark()
    assert a.seed == BENCHMARK_SEED and len(a.bubbles) == 100
    assert all(np.array_equal(p.vertices, q.vertices) for p, q in zip(a.bubbles, b.bubbles))
    assert all(len(m.faces) == 320 and len(m.vertices) == 162 for m in a.bubbles)
    assert np.all((a.radii >= 0.6) & (a.radii <= 1.2))
    assert a.size == (20.0, 20.0, 10.0) and len(a.liquid.faces) == 12
    assert a.liquid.attenuation == pytest.approx(0.1)
    assert all(m.attenuation == pytest.approx(-0.1) for m in a.bubbles)
    for m, c, r in zip(a.bubbles, a.centres, a.radii):
        assert np.allclose(np.linalg.norm(m.vertices - c, axis=1), r)  # spheres
        assert np.all(np.abs(m.vertices) <= np.array([10, 10, 5]) - 0.2 + 1e-9)
    assert pairwise_clearance(a.centres, a.radii) >= 0.1 - 1e-9
    assert len(a.items) == 101


def _roughness(phantom):
    """Largest jump of r/r0 along an edge, relative to the largest deviation, per bubble."""
    out = []
    for m, c, r in zip(phantom.bubbles, phantom.centres, phantom.radii):
        rr = np.linalg.norm(m.vertices - c, axis=1) / r
        e = np.asarray(m.faces)[:, :2]
        out.append(np.abs(rr[e[:, 0]] - rr[e[:, 1]]).max() / np.abs(rr - 1).max())
    return np.array(out)


def test_foam3d_is_smoothly_deformed_reproducible_and_disjoint():
    a = foam3d(5, n_bubbles=30, perturbation=0.08)
    b = foam3d(5, n_bubbles=30, perturbation=0.08)
    assert all(np.array_equal(p.vertices, q.vertices) for p, q in zip(a.bubbles, b.bubbles))
    bound = []
    for m, c, r in zip(a.bubbles, a.centres, a.radii):
        rr = np.linalg.norm(m.vertices - c, axis=1) / r
        assert 0.04 - 1e-12 <= np.abs(rr - 1).max() <= 0.08 + 1e-12
        bound.append(rr.max() * r)
    assert pairwise_clearance(a.centres, np.array(bound)) >= 0.1 - 1e-9
    assert not np.allclose(foam3d(6, n_bubbles=30).centres, a.centres)
    # smooth: halving the edge length (one more subdivision) about halves the jumps along edges
    fine = foam3d(5, n_bubbles=30, perturbation=0.08, subdivisions=3)
    assert np.median(_roughness(fine) / _roughness(a)) < 0.65
