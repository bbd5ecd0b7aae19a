"""Otsu binarisation and EDT bubble centres, on images with known disks and balls."""

import numpy as np
import pytest

from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.voxel.segment import binarise, bubble_centres, otsu_threshold

N = 200
EXT = (-5.0, 5.0, -5.0, 5.0)
PX = 10.0 / N
LIQUID = 0.1
CONTAINER = 4.6
# (x, y, r) in mm, separated by > 0.3 mm
BUBBLES = np.array([(-2.0, 1.5, 0.8), (1.3, 2.1, 0.6), (0.5, -2.2, 1.0), (-2.3, -1.7, 0.5), (2.5, -0.43, 0.7)])


def coords():
    x = EXT[0] + (np.arange(N) + 0.5) * PX
    y = EXT[3] - (np.arange(N) + 0.5) * PX  # row 0 at y max
    return np.meshgrid(x, y)


def foam_image(noise=0.0, seed=0):
    """Liquid disk (the container) with gas disks; outside the container is empty (dark too)."""
    X, Y = coords()
    img = np.where(X**2 + Y**2 < CONTAINER**2, LIQUID, 0.0)
    for cx, cy, r in BUBBLES:
        img[(X - cx) ** 2 + (Y - cy) ** 2 < r * r] = 0.0
    if noise:
        img = img + np.random.default_rng(seed).normal(0, noise, img.shape)
    return img


def container_roi(margin=0.2):
    X, Y = coords()
    return X**2 + Y**2 < (CONTAINER - margin) ** 2


def match(found, truth_xy, tol):
    """Each true centre has exactly one found centre within tol."""
    assert len(found) == len(truth_xy)
    d = np.linalg.norm(found[:, None, :] - truth_xy[None, :, :], axis=-1)
    assert np.all(d.min(axis=0) < tol)
    assert len(set(d.argmin(axis=0))) == len(truth_xy)
    return d.min(axis=0)


def test_otsu_threshold_separates_the_two_phases():
    t = otsu_threshold(foam_image(noise=0.01), roi=container_roi())
    assert 0.03 < t < 0.07
    with pytest.raises(ValueError, match="constant"):
        otsu_threshold(np.ones((5, 5)))


def test_binarise_counts_and_roi():
    img = foam_image(noise=0.01, seed=1)
    mask = binarise(img, opening_radius=1, roi=container_roi())
    X, Y = coords()
    truth = np.zeros_like(mask)
    for cx, cy, r in BUBBLES:
        truth |= (X - cx) ** 2 + (Y - cy) ** 2 < r * r
    assert mask.dtype == bool and mask.shape == img.shape
    dice = 2 * (mask & truth).sum() / (mask.sum() + truth.sum())
    assert dice > 0.97
    # without the roi, the empty space around the container is "bubble" too
    assert binarise(img, roi=None).sum() > 2 * mask.sum()
    # bright features: the same mask from the negated image
    inv = binarise(-img, roi=container_roi(), bubbles_are_dark=False)
    assert (inv ^ mask).sum() < 0.01 * mask.sum()


def test_opening_removes_salt_noise():
    img = foam_image()
    rng = np.random.default_rng(3)
    salt = rng.random(img.shape) < 0.003
    img[salt & container_roi()] = 0.0  # isolated dark pixels in the liquid
    noisy = binarise(img, opening_radius=0, roi=container_roi())
    clean = binarise(img, opening_radius=1, roi=container_roi())
    centres_noisy, _ = bubble_centres(noisy, EXT, min_distance=0.3)
    centres, radii = bubble_centres(clean, EXT, min_distance=0.3)
    assert len(centres_noisy) > len(BUBBLES) + 10
    match(centres, BUBBLES[:, :2], tol=PX)


def test_bubble_centres_and_radii():
    mask = binarise(foam_image(noise=0.01, seed=2), opening_radius=1, roi=container_roi())
    centres, radii = bubble_centres(mask, EXT, min_distance=0.4)
    assert centres.shape == (5, 2) and radii.shape == (5,)
    d = match(centres, BUBBLES[:, :2], tol=PX)
    assert d.max() < PX  # within a pixel
    order = np.argmin(np.linalg.norm(centres[:, None] - BUBBLES[None, :, :2], axis=-1), axis=1)
    np.testing.assert_allclose(radii, BUBBLES[order, 2], atol=1.5 * PX)
    assert np.all(np.diff(radii) <= 0)  # largest first


def test_touching_bubbles_are_split_by_min_distance():
    X, Y = coords()
    mask = ((X + 0.7) ** 2 + Y**2 < 0.8**2) | ((X - 0.7) ** 2 + Y**2 < 0.8**2)  # overlapping pair
    centres, _ = bubble_centres(mask, EXT, min_distance=0.5)
    match(centres, np.array([[-0.7, 0.0], [0.7, 0.0]]), tol=2 * PX)
    merged, _ = bubble_centres(mask, EXT, min_distance=2.0)
    assert len(merged) == 1


def ball_mask(shape, ext, balls):
    nz, ny, nx = shape
    x = ext[0] + (np.arange(nx) + 0.5) * (ext[1] - ext[0]) / nx
    y = ext[3] - (np.arange(ny) + 0.5) * (ext[3] - ext[2]) / ny
    z = ext[4] + (np.arange(nz) + 0.5) * (ext[5] - ext[4]) / nz
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    mask = np.zeros(shape, bool)
    for bx, by, bz, r in balls:
        mask |= (X - bx) ** 2 + (Y - by) ** 2 + (Z - bz) ** 2 < r * r
    return mask


def test_bubble_centres_3d_and_anisotropic_grid():
    ext = (-3.0, 3.0, -2.5, 2.5, -2.0, 2.0)
    balls = np.array([(-1.5, 1.0, 0.5, 0.8), (1.2, -0.9, -0.7, 0.6), (1.6, 1.2, 1.1, 0.5)])
    shape = (40, 50, 60)  # z, y, x; 0.1 mm voxels
    centres, radii = bubble_centres(ball_mask(shape, ext, balls), ext, min_distance=0.3)
    d = match(centres, balls[:, :3], tol=0.1)
    assert d.max() < 0.1
    order = np.argmin(np.linalg.norm(centres[:, None] - balls[None, :, :3], axis=-1), axis=1)
    np.testing.assert_allclose(radii, balls[order, 3], atol=0.15)
    # voxels twice as long along z (0.2 mm): same centres within a coarse voxel
    c2, r2 = bubble_centres(ball_mask((20, 50, 60), ext, balls), ext, min_distance=0.3)
    match(c2, balls[:, :3], tol=0.2)


def test_fbp_binarise_centres_end_to_end():
    """Analytic sinogram of the foam (container disk minus bubble disks) -> FBP -> Otsu -> EDT."""
    from bubsub.core.voxel.astra2d import reconstruct_2d  # ASTRA's FBP if installed, else numpy

    g = ScanGeometry.parallel(np.linspace(0, np.pi, 100, endpoint=False), pixel_size=0.05, cols=220)
    o, d = g.rays(2)

    def chords(cx, cy, r):
        w = np.array([cx, cy, 0.0]) - o
        t = np.sum(w * d, axis=-1)
        return 2 * np.sqrt(np.maximum(r * r - (np.sum(w * w, axis=-1) - t * t), 0))

    sino = LIQUID * chords(0.0, 0.0, CONTAINER)
    for cx, cy, r in BUBBLES:
        sino = sino - LIQUID * chords(cx, cy, r)
    sino = sino.mean(axis=-1).astype(np.float32)
    sino += np.random.default_rng(4).normal(0, 0.005, sino.shape).astype(np.float32)
    rec = reconstruct_2d("fbp", sino, g, (N, N), EXT)
    mask = binarise(rec, opening_radius=1, roi=container_roi(), fill_holes=True)
    centres, radii = bubble_centres(mask, EXT, min_distance=0.4, min_radius=0.2)
    match(centres, BUBBLES[:, :2], tol=PX)


def test_bad_input():
    with pytest.raises(ValueError, match="roi"):
        binarise(foam_image(), roi=np.ones((3, 3), bool))
    with pytest.raises(ValueError, match="opening_radius"):
        binarise(foam_image(), opening_radius=-1)
    with pytest.raises(ValueError, match="2D or 3D"):
        binarise(np.zeros(5))
    with pytest.raises(ValueError, match="grid extent"):
        bubble_centres(np.zeros((4, 4), bool), (0, 1, 0, 1, 0, 1))
    with pytest.raises(ValueError, match="min_distance"):
        bubble_centres(np.zeros((4, 4), bool), (0, 1, 0, 1), min_distance=0)
    with pytest.raises(ValueError, match="boolean"):
        bubble_centres(np.full((4, 4), 0.5), (0, 1, 0, 1))
    c, r = bubble_centres(np.zeros((4, 4), bool), (0, 1, 0, 1))
    assert c.shape == (0, 2) and r.shape == (0,)


@pytest.mark.parametrize("shape, radius", [((40, 50), (2, 3)), ((12, 20, 24), (1, 2, 3)), ((9, 9, 9), (4, 4, 4))])
def test_footprint_maxima_equal_scipy_maximum_filter(shape, radius):
    """The candidate-only maxima search gives exactly scipy's maximum_filter verdict (zeros outside the grid),
    plateaus and ties included."""
    from scipy import ndimage

    from bubsub.core.voxel.segment import _footprint_maxima

    rng = np.random.default_rng(sum(shape))
    values = np.round(ndimage.gaussian_filter(rng.random(shape), 1.5) * 20) / 20  # plateaus of equal values
    r = np.array(radius)
    g = np.indices(tuple(2 * r + 1)) - r.reshape((len(r),) + (1,) * len(r))
    foot = np.sum((g / r.reshape((len(r),) + (1,) * len(r))) ** 2, axis=0) <= 1.0
    foot |= np.sum(np.abs(g), axis=0) <= 1
    eligible = rng.random(shape) < 0.8
    expected = eligible & (values >= ndimage.maximum_filter(values, footprint=foot, mode="constant", cval=0.0))
    got = _footprint_maxima(values, foot, eligible)
    assert expected.sum() > 2
    np.testing.assert_array_equal(got, expected)
