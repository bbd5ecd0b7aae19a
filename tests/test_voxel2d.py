"""2D voxel reconstruction (ASTRA CPU and numpy backends) against analytic disk sinograms."""

import importlib.util

import numpy as np
import pytest

from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.voxel.grid import index_to_world, world_to_index
from bubsub.core.voxel.astra2d import AstraProjector2D, fbp_2d, reconstruct_2d
from bubsub.core.voxel.projector3d import VoxelProjector

needs_astra = pytest.mark.skipif(importlib.util.find_spec("astra") is None, reason="ASTRA toolbox not installed")

N = 96
PX = 0.1
EXT = (-N * PX / 2, N * PX / 2, -N * PX / 2, N * PX / 2)
# off-centre, with |x| != |y|: a flip of either axis or a transpose moves it
CENTRE = np.array([1.0, 3.0])
RADIUS = 1.5
MU = 0.1


def disk_sinogram(geom, centre, radius, mu, ss=4):
    """Exact line integrals of a uniform disk, averaged over ss rays per detector pixel.

    chord = 2 sqrt(r^2 - s^2) mu with s the distance of the ray from the centre.
    """
    o, d = geom.rays(ss)  # (n, cols, ss, 3), ray directions
    w = np.array([centre[0], centre[1], 0.0]) - o
    t = np.sum(w * d, axis=-1)
    s2 = np.sum(w * w, axis=-1) - t * t
    return (2 * np.sqrt(np.maximum(radius**2 - s2, 0)) * mu).mean(axis=-1).astype(np.float32)


def disk_image(centre, radius, mu, ss=4):
    """Disk rasterised with ss x ss sub-pixels (independent of the grid module)."""
    x = EXT[0] + (np.arange(N) + 0.5) * PX
    y = EXT[3] - (np.arange(N) + 0.5) * PX  # row 0 at y max
    off = ((np.arange(ss) + 0.5) / ss - 0.5) * PX
    img = np.zeros((N, N))
    for a in off:
        for b in off:
            img += ((x[None, :] + a - centre[0]) ** 2 + (y[:, None] + b - centre[1]) ** 2) <= radius**2
    return img / ss**2 * mu


def region_mean(rec, x0, y0, radius=0.5):
    """Mean of rec over pixel centres within radius of (x0, y0), pixel positions by hand."""
    yy, xx = np.mgrid[0:N, 0:N]
    x = EXT[0] + (xx + 0.5) * PX
    y = EXT[3] - (yy + 0.5) * PX  # row 0 at y max
    return rec[np.hypot(x - x0, y - y0) < radius].mean()


def check_disk(rec, tol_mu=0.03, tol_px=0.5):
    """mu inside, ~0 outside, centroid position, and orientation of a disk reconstruction."""
    assert rec.shape == (N, N) and rec.dtype == np.float32
    yy, xx = np.mgrid[0:N, 0:N]
    x = EXT[0] + (xx + 0.5) * PX
    y = EXT[3] - (yy + 0.5) * PX
    r = np.hypot(x - CENTRE[0], y - CENTRE[1])
    inner = r < RADIUS - 0.4
    outer = (r > RADIUS + 0.5) & (np.hypot(x, y) < 4.5)
    assert abs(rec[inner].mean() - MU) < tol_mu * MU
    assert abs(rec[outer].mean()) < 0.05 * MU
    mask = rec > MU / 2
    centroid = index_to_world(np.argwhere(mask).mean(axis=0), (N, N), EXT)
    assert np.linalg.norm(centroid - CENTRE) < tol_px * PX
    # orientation: the disk is at (1.0, 3.0), not at any mirror or transpose of it
    assert region_mean(rec, *CENTRE) > 0.9 * MU
    for x_, y_ in [(CENTRE[0], -CENTRE[1]), (-CENTRE[0], CENTRE[1]), (CENTRE[1], CENTRE[0])]:
        assert abs(region_mean(rec, x_, y_)) < 0.1 * MU


@pytest.fixture(scope="module")
def parallel():
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 90, endpoint=False), pixel_size=0.1, cols=128)
    return g, disk_sinogram(g, CENTRE, RADIUS, MU)


@pytest.fixture(scope="module")
def fan():
    g = ScanGeometry.cone(
        np.linspace(0, 2 * np.pi, 120, endpoint=False), source_origin=300.0, origin_detector=15.0,
        pixel_size=0.1, cols=128,
    )
    return g, disk_sinogram(g, CENTRE, RADIUS, MU)


def test_grid_conversions_match_the_image_convention():
    # pixel (row 0, col 0) is the top-left pixel: x min, y max
    np.testing.assert_allclose(index_to_world([0, 0], (N, N), EXT), [EXT[0] + PX / 2, EXT[3] - PX / 2])
    np.testing.assert_allclose(world_to_index([EXT[1] - PX / 2, EXT[2] + PX / 2], (N, N), EXT), [N - 1, N - 1])
    rng = np.random.default_rng(0)
    p = rng.uniform(-4, 4, (10, 2))
    np.testing.assert_allclose(index_to_world(world_to_index(p, (N, N), EXT), (N, N), EXT), p, atol=1e-12)


@needs_astra
@pytest.mark.parametrize("kind", ["parallel", "fan"])
def test_astra_forward_matches_analytic_chords(kind, parallel, fan):
    g, sino = parallel if kind == "parallel" else fan
    with AstraProjector2D(g, (N, N), EXT) as A:
        s = A.forward(disk_image(CENTRE, RADIUS, MU))
    assert s.shape == g.shape and s.dtype == np.float32
    assert np.linalg.norm(s - sino) / np.linalg.norm(sino) < 0.02


@pytest.mark.parametrize("kind", ["parallel", "fan"])
def test_projectors_are_adjoint(kind, parallel, fan):
    g, _ = parallel if kind == "parallel" else fan
    rng = np.random.default_rng(1)
    x = rng.random((N, N)).astype(np.float32)
    y = rng.random(g.shape).astype(np.float32)
    ops = [VoxelProjector(g, (N, N), EXT)]
    if importlib.util.find_spec("astra") is not None:
        ops.append(AstraProjector2D(g, (N, N), EXT))
    for op in ops:
        lhs = np.dot(op.forward(x).ravel().astype(float), y.ravel())
        rhs = np.dot(x.ravel().astype(float), op.adjoint(y).ravel())
        assert lhs == pytest.approx(rhs, rel=1e-5)


def test_numpy_projector_matches_analytic_chords(parallel, fan):
    for g, sino in (parallel, fan):
        s = VoxelProjector(g, (N, N), EXT).forward(disk_image(CENTRE, RADIUS, MU))
        assert np.linalg.norm(s - sino) / np.linalg.norm(sino) < 0.03


@pytest.mark.parametrize("backend", [pytest.param("astra", marks=needs_astra), "numpy"])
def test_fbp_parallel(parallel, backend):
    g, sino = parallel
    check_disk(fbp_2d(sino, g, (N, N), EXT, backend=backend))


@needs_astra
def test_fbp_fan_and_astra_refusal(fan):
    g, sino = fan
    check_disk(fbp_2d(sino, g, (N, N), EXT))  # auto -> numpy FBP for fan beams
    with pytest.raises(ValueError, match="plain parallel"):
        fbp_2d(sino, g, (N, N), EXT, backend="astra")


@needs_astra
def test_fbp_accepts_pixel_size_and_astra_dict(parallel):
    g, sino = parallel
    a = fbp_2d(sino, g, (N, N), pixel_size=PX)
    b = reconstruct_2d("fbp", sino, g.to_astra(), (N, N), EXT)
    np.testing.assert_allclose(a, b, atol=1e-6)


@needs_astra
@pytest.mark.parametrize(
    "method, iterations",
    [("sirt", 150), ("cgls", 20), ("lsqr", 20)],
)
def test_iterative_astra(parallel, fan, method, iterations):
    for g, sino in (parallel, fan):
        check_disk(reconstruct_2d(method, sino, g, (N, N), EXT, iterations=iterations))


@pytest.mark.parametrize("method, iterations", [("sirt", 100), ("cgls", 15)])
def test_iterative_numpy(parallel, method, iterations):
    g, sino = parallel
    check_disk(reconstruct_2d(method, sino, g, (N, N), EXT, iterations=iterations, backend="numpy"))


@needs_astra
def test_sirt_nonneg_and_x0(parallel):
    g, sino = parallel
    rec = reconstruct_2d("sirt", sino, g, (N, N), EXT, iterations=30, nonneg=True)
    assert rec.min() >= 0
    # a warm start at the truth stays there
    truth = disk_image(CENTRE, RADIUS, MU).astype(np.float32)
    with AstraProjector2D(g, (N, N), EXT) as A:
        exact = A.forward(truth)
    warm = reconstruct_2d("cgls", exact, g, (N, N), EXT, iterations=3, x0=truth)
    assert np.abs(warm - truth).max() < 1e-3
    # a warm start near the truth beats a cold start (ASTRA's own CGLS gets this wrong)
    near = truth + np.float32(0.01) * np.random.default_rng(3).random(truth.shape, dtype=np.float32)
    cold = reconstruct_2d("cgls", exact, g, (N, N), EXT, iterations=5)
    warm = reconstruct_2d("cgls", exact, g, (N, N), EXT, iterations=5, x0=near)
    assert np.abs(warm - truth).max() < 0.5 * np.abs(cold - truth).max()


@needs_astra
def test_tv_beats_fbp_on_noisy_sparse_data():
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 25, endpoint=False), pixel_size=0.1, cols=128)
    sino = disk_sinogram(g, CENTRE, RADIUS, MU)
    noisy = sino + np.random.default_rng(2).normal(0, 0.01, sino.shape).astype(np.float32)
    truth = disk_image(CENTRE, RADIUS, MU)
    fbp = reconstruct_2d("fbp", noisy, g, (N, N), EXT)
    tv = reconstruct_2d("tv", noisy, g, (N, N), EXT, tv_weight=5e-3, iterations=200, nonneg=True)
    aniso = reconstruct_2d("tv", noisy, g, (N, N), EXT, tv_weight=5e-3, iterations=200, isotropic=False)
    assert tv.min() >= 0
    rmse = lambda a: np.sqrt(np.mean((a - truth) ** 2))  # noqa: E731
    assert rmse(tv) < 0.5 * rmse(fbp)
    assert rmse(aniso) < 0.7 * rmse(fbp)
    check_disk(tv, tol_mu=0.05)


@needs_astra
def test_bad_input(parallel):
    g, sino = parallel
    with pytest.raises(ValueError, match="unknown method"):
        reconstruct_2d("art", sino, g, (N, N), EXT)
    with pytest.raises(ValueError, match="shape"):
        reconstruct_2d("sirt", sino[:, :-1], g, (N, N), EXT)
    with pytest.raises(ValueError, match="tv_weight"):
        reconstruct_2d("tv", sino, g, (N, N), EXT)
    with pytest.raises(ValueError, match="extent or a pixel_size"):
        reconstruct_2d("fbp", sino, g, (N, N))
    with pytest.raises(ValueError, match="not both"):
        reconstruct_2d("fbp", sino, g, (N, N), EXT, pixel_size=0.1)
    with pytest.raises(ValueError, match="2D geometry"):
        g3 = ScanGeometry.parallel([0.0, 1.0], pixel_size=0.1, cols=8, rows=4)
        reconstruct_2d("fbp", np.zeros(g3.shape), g3, (N, N), EXT)
    bad = sino.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        reconstruct_2d("cgls", bad, g, (N, N), EXT)
