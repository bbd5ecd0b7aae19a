"""Simulated scans: ASTRA voxel projection vs analytic chords, noise statistics, 3D mesh path."""

import numpy as np
import pytest

from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.projection.mesh import Polygon
from bubsub.core.foam.containers import liquid_box
from bubsub.core.foam.phantoms import foam2d, foam3d
from bubsub.core.projection.projector import MeshProjector
from bubsub.core.projection.masks import rasterize
from bubsub.core.foam.simulate import (
    add_poisson_noise,
    default_geometry_2d,
    default_geometry_3d,
    project_image,
    simulate_2d,
    simulate_3d,
)


def disk(centre, r, mu, n=512):
    t = 2 * np.pi * np.arange(n) / n
    return Polygon(np.c_[centre[0] + r * np.cos(t), centre[1] + r * np.sin(t)], mu)


def detector_coords(geometry):
    return (np.arange(geometry.det_count) - geometry.det_count / 2 + 0.5)


# -- ASTRA 2D projection ---------------------------------------------------------------------------
@pytest.mark.parametrize("projector", ["linear", "strip"])
def test_astra_projection_of_an_offcentre_disk_matches_the_chord(projector):
    centre, r, mu = np.array([1.1, -0.6]), 0.9, 0.1
    ext = (-2.5, 2.5, -2.5, 2.5)
    img = rasterize([disk(centre, r, mu)], (500, 500), ext, supersample=3)
    angles = np.array([0.0, 0.7, np.pi / 2, 2.2])
    dpx = 0.01
    g = ScanGeometry.parallel(angles, pixel_size=dpx, cols=720)
    sino = project_image(img, ext, g, projector=projector)
    assert sino.shape == (4, 720) and sino.dtype == np.float32
    s = detector_coords(g) * dpx
    for i, th in enumerate(angles):
        # detector u = (cos th, sin th): the disk centre projects to centre . u
        sc = centre @ np.array([np.cos(th), np.sin(th)])
        chord = 2 * mu * np.sqrt(np.clip(r * r - (s - sc) ** 2, 0, None))
        inner = np.abs(s - sc) < 0.9 * r
        assert np.abs(sino[i][inner] - chord[inner]).max() < 0.02 * 2 * mu * r
        # the integral over the detector is the disk's mass for every angle
        assert sino[i].sum() * dpx == pytest.approx(mu * np.pi * r * r, rel=2e-3)
        # and nothing is seen outside the shadow
        assert np.abs(sino[i][np.abs(s - sc) > r + 0.03]).max() < 1e-6


def test_astra_fan_beam_agrees_with_the_mesh_projector():
    d = disk((0.5, 0.8), 0.7, 0.2)
    ext = (-2.0, 2.0, -2.0, 2.0)
    img = rasterize([d], (400, 400), ext, supersample=3)
    g = ScanGeometry.cone(np.linspace(0, 2 * np.pi, 5, endpoint=False), source_origin=20.0,
                          origin_detector=10.0, pixel_size=0.015, cols=400)
    assert g.kind == "fanflat_vec"
    vox = project_image(img, ext, g)
    exact = MeshProjector(g).forward([d])
    assert exact.max() > 0.25
    assert np.abs(vox - exact).mean() < 2e-3
    assert np.abs(vox - exact).max() < 0.05


def test_project_image_bad_input():
    g = default_geometry_2d(3, det_count=50, pixel_size=0.1)
    img = np.zeros((10, 10))
    with pytest.raises(ValueError, match="square"):
        project_image(np.zeros((10, 20)), (-1, 1, -1, 1), g)
    with pytest.raises(ValueError, match="does not support"):
        project_image(img, (-1, 1, -1, 1), g, projector="line_fanflat")
    with pytest.raises(ValueError, match="NaN"):
        project_image(np.full((10, 10), np.nan), (-1, 1, -1, 1), g)
    with pytest.raises(ValueError, match="2D ScanGeometry"):
        project_image(img, (-1, 1, -1, 1), default_geometry_3d(2, rows=4, cols=4))


# -- noise ------------------------------------------------------------------------------------------
def test_poisson_noise_statistics():
    p = np.full(400_000, 1.0)
    i0 = 1000.0
    noisy = add_poisson_noise(p, i0, seed=11)
    assert noisy.dtype == np.float32 and noisy.shape == p.shape
    lam = i0 * np.exp(-1.0)  # expected counts
    # delta method: mean p + 1/(2 lam), variance 1/lam
    assert noisy.mean() == pytest.approx(1.0 + 1 / (2 * lam), abs=3e-4)
    assert noisy.var() == pytest.approx(1 / lam, rel=0.02)
    # counts are integers: exp(-p) * I0 lands on integers
    counts = i0 * np.exp(-noisy.astype(np.float64))
    assert np.allclose(counts, np.round(counts), atol=1e-3 * counts.max())


def test_poisson_noise_is_seeded_and_clamps_zero_counts():
    p = np.linspace(0, 2, 1000)
    a, b, c = (add_poisson_noise(p, 100.0, seed=s) for s in (3, 3, 4))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    dark = add_poisson_noise(np.full(100, 50.0), 100.0, seed=0)  # essentially no photons arrive
    assert np.allclose(dark, np.log(100.0))
    for bad in (0, -5, np.inf, None):
        with pytest.raises(ValueError, match="photons"):
            add_poisson_noise(p, bad)
    with pytest.raises(ValueError, match="seed"):
        add_poisson_noise(p, 100.0, seed=-1)


# -- 2D scans ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small2d():
    return foam2d(4, n_bubbles=8)


def test_simulate_2d_bubble_data_matches_exact_polygon_projection(small2d):
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 6, endpoint=False), pixel_size=0.025, cols=600)
    scan = simulate_2d(small2d, g, image_size=800, supersample=2)
    assert scan.data.shape == (6, 600) and scan.background.shape == (6, 600)
    assert scan.bubble_contrast == pytest.approx(-0.1)
    exact = MeshProjector(g).forward(list(small2d.bubbles))
    err = np.linalg.norm(scan.bubble_data - exact) / np.linalg.norm(exact)
    assert err < 0.02
    # mass: every projection of the bubbles integrates to contrast x total area
    mass = -0.1 * sum(b.area for b in small2d.bubbles)
    assert np.allclose(scan.bubble_data.sum(axis=1) * 0.025, mass, rtol=5e-3)
    # background: the liquid square alone, 10 mm x 0.1/mm through the middle at angle 0
    s = detector_coords(g) * 0.025
    assert np.allclose(scan.background[0][np.abs(s) < 4.9], 1.0, atol=1e-3)
    # the mesh method gives the same bubbles exactly
    mesh_scan = simulate_2d(small2d, g, method="mesh")
    assert np.allclose(mesh_scan.bubble_data, exact, atol=1e-4)  # float32, projector eps


def test_simulate_2d_noise_is_reproducible_and_on_the_full_projection(small2d):
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 4, endpoint=False), pixel_size=0.05, cols=300)
    clean = simulate_2d(small2d, g, image_size=400)
    a = simulate_2d(small2d, g, image_size=400, photons=1e4, seed=5)
    b = simulate_2d(small2d, g, image_size=400, photons=1e4, seed=5)
    c = simulate_2d(small2d, g, image_size=400, photons=1e4, seed=6)
    assert np.array_equal(a.data, b.data) and not np.array_equal(a.data, c.data)
    assert np.array_equal(a.background, clean.background)  # background stays noise-free
    resid = (a.data - clean.data)[:, 60:240]  # inside the liquid's shadow
    lam = 1e4 * np.exp(-clean.data[:, 60:240])
    z = resid / np.sqrt(1 / lam)
    assert abs(z.mean()) < 0.2 and 0.8 < z.std() < 1.2
    assert a.attrs["photons"] == 1e4 and a.attrs["noise_seed"] == 5


def test_default_geometry_2d_covers_the_phantom_diagonal():
    g = default_geometry_2d(10)
    assert g.shape == (10, 2400) and g.kind == "parallel_vec"
    assert 2400 * 0.006 > 10 * np.sqrt(2)


def test_simulate_bad_input(small2d):
    g2 = default_geometry_2d(2, det_count=40, pixel_size=0.5)
    with pytest.raises(ValueError, match="needs a 3D phantom, got a 2D"):
        simulate_3d(small2d, default_geometry_3d(2, rows=4, cols=4))
    with pytest.raises(ValueError, match="method"):
        simulate_2d(small2d, g2, method="magic")
    with pytest.raises(ValueError, match="FoamPhantom"):
        simulate_2d(list(small2d.bubbles), g2)
    with pytest.raises(ValueError, match="2D ScanGeometry"):
        simulate_2d(small2d, default_geometry_3d(2, rows=4, cols=4))


# -- 3D scans ---------------------------------------------------------------------------------------
def test_simulate_3d_mass_and_background_with_the_mesh_projector():
    ph = foam3d(2, n_bubbles=6, size=(8.0, 8.0, 4.0), radius_range=(0.6, 1.0))
    px = 0.1
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 3, endpoint=False), pixel_size=px, cols=130, rows=50)
    scan = simulate_3d(ph, g)
    assert scan.data.shape == (3, 50, 130) and scan.data.dtype == np.float32
    total = -0.1 * sum(b.volume for b in ph.bubbles)
    assert np.allclose(scan.bubble_data.sum(axis=(1, 2)) * px * px, total, rtol=0.01)
    # the box alone: 8 mm of liquid at 0.1/mm straight through at angle 0
    assert scan.background[0, 25, 65] == pytest.approx(0.8, abs=1e-4)
    assert np.allclose(scan.background, MeshProjector(g).forward([liquid_box((8, 8, 4))]))
    noisy = simulate_3d(ph, g, photons=1e3, seed=1)
    assert not np.array_equal(noisy.data, scan.data)
    assert np.array_equal(noisy.background, scan.background)


def test_default_cone_geometry_sees_the_whole_box():
    g = default_geometry_3d(4, rows=32, cols=64)
    assert g.kind == "cone_vec" and g.shape == (4, 32, 64)
    bg = MeshProjector(g).forward([liquid_box((20, 20, 10))])
    assert bg.max() > 1.0
    # the box's shadow ends inside the detector on every side
    assert np.all(bg[:, [0, -1], :] == 0) and np.all(bg[:, :, [0, -1]] == 0)
    assert np.all(bg[:, 16, 32] > 0)
