"""numpy voxel projector, FDK and iterative 3D reconstruction against analytic balls."""

import numpy as np
import pytest

from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.voxel.grid import grid_extent, index_to_world, world_to_index
from bubsub.core.voxel.fdk import fdk, ramp_filter
from bubsub.core.voxel.projector3d import VoxelProjector
from bubsub.core.voxel.reconstruct3d import reconstruct_3d

SHAPE = (32, 48, 48)  # (z, y, x)
H = 0.2
EXT = grid_extent(SHAPE, H)  # (-4.8, 4.8, -4.8, 4.8, -3.2, 3.2)
CENTRE = np.array([1.5, -2.0, 1.4])  # x, y, z: off-centre on every axis
RADIUS = 1.2
MU = 0.1


def ball_projections(geom, centre, radius, mu, ss=3):
    """Exact line integrals of a uniform ball, ss x ss rays per pixel (chord = 2 sqrt(r^2 - s^2))."""
    o, d = geom.rays(ss)
    w = np.asarray(centre, float) - o
    t = np.sum(w * d, axis=-1)
    s2 = np.sum(w * w, axis=-1) - t * t
    return (2 * np.sqrt(np.maximum(radius**2 - s2, 0)) * mu).mean(axis=-1).astype(np.float32)


def ball_volume(shape, extent, centre, radius, mu, ss=3):
    """Ball rasterised with ss^3 sub-voxels; coordinates written out by hand (vol[z, y, x], y down)."""
    nz, ny, nx = shape
    hx = (extent[1] - extent[0]) / nx
    hy = (extent[3] - extent[2]) / ny
    hz = (extent[5] - extent[4]) / nz
    x = extent[0] + (np.arange(nx) + 0.5) * hx
    y = extent[3] - (np.arange(ny) + 0.5) * hy
    z = extent[4] + (np.arange(nz) + 0.5) * hz
    off = (np.arange(ss) + 0.5) / ss - 0.5
    v = np.zeros(shape)
    for a in off:
        for b in off:
            for c in off:
                v += (
                    (x[None, None, :] + a * hx - centre[0]) ** 2
                    + (y[None, :, None] + b * hy - centre[1]) ** 2
                    + (z[:, None, None] + c * hz - centre[2]) ** 2
                ) <= radius**2
    return (v / ss**3 * mu).astype(np.float32)


@pytest.fixture(scope="module")
def cone():
    g = ScanGeometry.cone(
        np.linspace(0, 2 * np.pi, 40, endpoint=False), source_origin=300.0, origin_detector=15.0,
        pixel_size=0.15, cols=96, rows=64,
    )
    return g, ball_projections(g, CENTRE, RADIUS, MU)


@pytest.fixture(scope="module")
def par3d():
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 30, endpoint=False), pixel_size=0.15, cols=96, rows=64)
    return g, ball_projections(g, CENTRE, RADIUS, MU)


def check_ball(rec, tol_mu=0.03, tol_vox=1.0, tol_mirror=0.2):
    """Value inside, centre and radius (from the volume above mu/2) of a reconstructed ball."""
    assert rec.shape == SHAPE and rec.dtype == np.float32
    ref = ball_volume(SHAPE, EXT, CENTRE, RADIUS - 0.5, 1.0) >= 1.0  # well inside
    assert abs(rec[ref].mean() - MU) < tol_mu * MU
    mask = rec > MU / 2
    centre = index_to_world(np.argwhere(mask).mean(axis=0), SHAPE, EXT)
    assert np.linalg.norm(centre - CENTRE) < tol_vox * H
    radius = (mask.sum() * H**3 * 3 / (4 * np.pi)) ** (1 / 3)
    assert abs(radius - RADIUS) < tol_vox * H
    # orientation: the slice/row/col holding the centre, computed by hand
    z, r, c = int((CENTRE[2] - EXT[4]) / H), int((EXT[3] - CENTRE[1]) / H), int((CENTRE[0] - EXT[0]) / H)
    assert rec[z, r, c] > 0.9 * MU
    assert abs(rec[SHAPE[0] - 1 - z, r, c]) < tol_mirror * MU  # z mirrored
    assert abs(rec[z, SHAPE[1] - 1 - r, c]) < tol_mirror * MU  # y mirrored


def test_grid_3d_conventions():
    np.testing.assert_allclose(index_to_world([0, 0, 0], SHAPE, EXT), [EXT[0] + H / 2, EXT[3] - H / 2, EXT[4] + H / 2])
    p = np.array([[1.2, -0.8, 0.9], [-4.7, 4.7, -3.1]])
    np.testing.assert_allclose(index_to_world(world_to_index(p, SHAPE, EXT), SHAPE, EXT), p, atol=1e-12)
    np.testing.assert_allclose(world_to_index(p[1], SHAPE, EXT), [0.0, 0.0, 0.0], atol=1e-9)


@pytest.mark.parametrize("binning", ["auto", 1.0])
def test_forward_matches_analytic_chords(cone, binning):
    g, truth = cone
    P = VoxelProjector(g, SHAPE, EXT, detector_binning=binning)
    p = P.forward(ball_volume(SHAPE, EXT, CENTRE, RADIUS, MU))
    assert p.shape == g.shape and p.dtype == np.float32
    assert p.sum() == pytest.approx(truth.sum(), rel=2e-3)  # mass: the amplitudes are right
    err = np.linalg.norm(p - truth) / np.linalg.norm(truth)
    inner = truth > 0.8 * truth.max()  # away from the blurred edges of the ball's shadow
    inner_err = np.abs(p - truth)[inner].max() / truth.max()
    if binning == "auto":
        assert err < 0.08
        assert inner_err < 0.03
    else:  # voxel shadow ~1.4 pixels splatted onto single pixels: gaps, the reason for binning
        assert inner_err > 0.1


def test_forward_small_voxels_and_parallel(par3d):
    # voxels smaller than pixels (virtual detector finer than the real one), parallel beam
    g, truth = par3d
    shape = (64, 96, 96)
    ext = grid_extent(shape, 0.1)
    P = VoxelProjector(g, shape, ext)
    assert np.all(P.binning[1] < 1)
    p = P.forward(ball_volume(shape, ext, CENTRE, RADIUS, MU, ss=2))
    assert np.linalg.norm(p - truth) / np.linalg.norm(truth) < 0.05
    inner = truth > 0.8 * truth.max()
    assert np.abs(p - truth)[inner].max() < 0.02 * truth.max()


@pytest.mark.parametrize("kind", ["cone", "par3d", "helical_tilted"])
def test_adjoint_is_exact(cone, par3d, kind):
    if kind == "helical_tilted":
        g0 = cone[0]
        v = np.array(g0.vectors)
        v[:, 2] += np.linspace(-1, 1, len(v))  # source rises: z-dependent maps everywhere
        v[:, 5] += np.linspace(-1, 1, len(v))
        v[:, 9:12] = v[:, 9:12] + 0.1 * v[:, 6:9]  # detector v not orthogonal to u
        g = ScanGeometry.from_astra("cone_vec", v, g0.det_rows, g0.det_cols)
    else:
        g = (cone if kind == "cone" else par3d)[0]
    rng = np.random.default_rng(0)
    P = VoxelProjector(g, SHAPE, EXT, threads=2)
    x = rng.random(SHAPE, dtype=np.float32)
    y = rng.random(g.shape, dtype=np.float32)
    lhs = np.dot(P.forward(x).ravel().astype(float), y.ravel())
    rhs = np.dot(x.ravel().astype(float), P.adjoint(y).ravel())
    assert lhs == pytest.approx(rhs, rel=1e-5)


def test_threads_and_slabs_do_not_change_results(cone):
    g, truth = cone
    x = ball_volume(SHAPE, EXT, CENTRE, RADIUS, MU)
    a = VoxelProjector(g, SHAPE, EXT, threads=1, slab_voxels=10**9)
    b = VoxelProjector(g, SHAPE, EXT, threads=2, slab_voxels=3000)
    np.testing.assert_allclose(a.forward(x), b.forward(x), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(a.adjoint(truth), b.adjoint(truth), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("filt", ["ram-lak", "shepp-logan"])
def test_fdk_recovers_the_ball(cone, filt):
    g, truth = cone
    check_ball(fdk(truth, g, SHAPE, EXT, filter=filt))


def test_fbp_parallel3d_recovers_the_ball(par3d):
    g, truth = par3d
    check_ball(reconstruct_3d("fbp", truth, g, SHAPE, EXT))


def test_fdk_nonuniform_angles_and_pixel_size(cone):
    # every other projection dropped from one half: angular weights keep the scale right
    g, truth = cone
    keep = np.r_[0:20:2, 20:40]
    rec = fdk(truth[keep], g[keep], SHAPE, pixel_size=H)
    check_ball(rec, tol_mu=0.05, tol_vox=1.5, tol_mirror=0.5)


def test_ramp_filter_response():
    H_, npad = ramp_filter(100, 0.5)
    f = np.fft.rfftfreq(npad) / 0.5  # cycles per mm
    # close to |f| (the ramp), exactly 0 at DC up to the band-limited kernel's offset
    assert npad >= 200
    np.testing.assert_allclose(H_[10:-10], f[10:-10], rtol=0.05, atol=2e-3)
    with pytest.raises(ValueError, match="unknown filter"):
        ramp_filter(10, 1.0, "gauss")


@pytest.mark.parametrize("method, iterations", [("sirt", 40), ("cgls", 10)])
def test_iterative_3d(cone, method, iterations):
    g, truth = cone
    rec = reconstruct_3d(method, truth, g, SHAPE, EXT, iterations=iterations)
    check_ball(rec, tol_mu=0.05, tol_vox=1.0)


def test_cgls_residual_decreases(cone):
    g, truth = cone
    P = VoxelProjector(g, SHAPE, EXT)
    res = []
    from bubsub.core.voxel.solvers import cgls

    cgls(P, truth, 6, callback=lambda k, x: res.append(np.linalg.norm(P.forward(x) - truth)))
    assert len(res) == 6
    assert all(b < a for a, b in zip(res, res[1:]))
    assert res[-1] < 0.1 * np.linalg.norm(truth)


def test_tv_3d_nonneg(cone):
    g, truth = cone
    noisy = truth + np.random.default_rng(1).normal(0, 0.02, truth.shape).astype(np.float32)
    rec = reconstruct_3d("tv", noisy, g, SHAPE, EXT, iterations=30, tv_weight=0.01, nonneg=True)
    assert rec.min() >= 0
    check_ball(rec, tol_mu=0.08, tol_vox=1.0)


def test_2d_geometries_through_the_numpy_path():
    g = ScanGeometry.cone(np.linspace(0, 2 * np.pi, 60, endpoint=False), source_origin=300.0,
                          origin_detector=15.0, pixel_size=0.15, cols=96)
    truth = ball_projections(g, [CENTRE[0], CENTRE[1], 0.0], RADIUS, MU)
    rec = reconstruct_3d("fdk", truth, g, SHAPE[1:], EXT[:4])
    assert rec.shape == SHAPE[1:]
    r, c = int((EXT[3] - CENTRE[1]) / H), int((CENTRE[0] - EXT[0]) / H)
    assert rec[r, c] == pytest.approx(MU, rel=0.05)
    assert abs(rec[SHAPE[1] - 1 - r, c]) < 0.1 * MU


def test_bad_input(cone):
    g, truth = cone
    with pytest.raises(ValueError, match="source plane"):
        VoxelProjector(g, (10, 10, 10), grid_extent((10, 10, 10), 70.0))
    P = VoxelProjector(g, SHAPE, EXT)
    with pytest.raises(ValueError, match="shape"):
        P.forward(np.zeros((2, 2, 2)))
    with pytest.raises(ValueError, match="shape"):
        P.adjoint(np.zeros((3, 4, 5)))
    with pytest.raises(ValueError, match="3D geometry"):
        VoxelProjector(g, (48, 48), EXT[:4])
    with pytest.raises(ValueError, match="unknown method"):
        reconstruct_3d("art", truth, g, SHAPE, EXT)
    with pytest.raises(ValueError, match="detector_binning"):
        VoxelProjector(g, SHAPE, EXT, detector_binning="big")
    with pytest.raises(ValueError, match="threads"):
        VoxelProjector(g, SHAPE, EXT, threads=0)
    with pytest.raises(ValueError, match="geometry"):
        VoxelProjector("cone", SHAPE, EXT)


def test_a_voxel_grid_is_one_object_every_voxel_driver_takes():
    from bubsub.core.voxel.grid import VoxelGrid, resolve_grid

    grid = VoxelGrid.of((4, 6, 8), pixel_size=0.5, centre=[1.0, 0.0, -1.0])
    assert grid.shape == (4, 6, 8) and grid.extent == (-1.0, 3.0, -1.5, 1.5, -2.0, 0.0)
    shape, extent = grid  # unpacks where the pair is expected
    np.testing.assert_allclose(grid.voxel_sizes, [0.5, 0.5, 0.5])
    np.testing.assert_allclose(grid.centre, [1.0, 0.0, -1.0])
    np.testing.assert_allclose(grid.index_to_world(grid.world_to_index([[0.3, -0.7, -1.2]])), [[0.3, -0.7, -1.2]])
    assert resolve_grid(grid) == grid
    with pytest.raises(ValueError, match="whole grid"):
        resolve_grid(grid, extent)
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 5, endpoint=False), pixel_size=0.5, cols=10, rows=6)
    op = VoxelProjector(g, grid)
    assert op.grid == grid and op.shape == shape and op.forward(np.ones(shape, np.float32)).shape == g.shape
    by_pair = reconstruct_3d("sirt", op.forward(np.ones(shape, np.float32)), g, shape, extent, iterations=2)
    np.testing.assert_array_equal(reconstruct_3d("sirt", op.forward(np.ones(shape, np.float32)), g, grid,
                                                 iterations=2), by_pair)
