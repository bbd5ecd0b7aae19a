"""Small bubbles and edge caps: balls of 5.5 pixels' radius, one beside a larger bubble, and caps cut by the
detector's top and bottom rows whose visible part is a ball of about 8 pixels, each found by ``reconstruct``."""

import numpy as np
import pytest

from bubsub.bench.matching import match
from bubsub.core.foam.ellipsoids import ellipsoid_labels, project_cylinder, project_ellipsoids
from bubsub.core.io.scanfile import Scan
from bubsub.core.metrics import label_image
from bubsub.core.projection.geometry import ScanGeometry
from bubsub.clients.pipeline.inputs.fov import field_of_view
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, reconstruct

C = -0.1
PX = 0.012  # mm: 384 columns, as the flowing foam's detector, so that the preview's voxel is 2.4 pixels


def _scan():
    """20 parallel views of 32 x 384 pixels (half height 16 pixels) of a liquid cylinder: three balls of 14
    pixels' radius, four of 5.5 (one 1.5 pixels from a large one), two caps of balls of 12 pixels seen 8 pixels
    deep (top and bottom); exact chords, Gaussian noise of 0.2 % of the deepest bubble signal. The preview's
    voxel is 2.4 pixels (160 across the field of view): a small ball is 2.3 voxels in radius, about the
    ball of the distance-transform detector's opening."""
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 20, endpoint=False), pixel_size=PX, cols=384, rows=32)
    half = field_of_view(g)[1]
    r_small, r_big, r_cap = 5.5 * PX, 14 * PX, 12 * PX
    centres = np.array([[-0.5, -0.5, 0.0], [0.6, -0.6, PX], [0.0, 0.9, -PX],
                        [0.5, 0.3, 0.0], [-0.8, 0.6, 2 * PX], [0.2, -1.0, -3 * PX],
                        [-0.5 + r_big + r_small + 1.5 * PX, -0.5, PX],
                        [1.0, -0.2, half + r_cap - 8 * PX], [-0.3, 1.1, -half - r_cap + 8 * PX]])
    radii = np.array([r_big] * 3 + [r_small] * 4 + [r_cap] * 2)
    axes = np.repeat(radii[:, None], 3, axis=1)
    rot = np.stack([np.eye(3)] * len(radii))
    background = project_cylinder(g, 2.0, (-1.0, 1.0), 0.1, 2)
    data = project_ellipsoids(g, centres, axes, rot, C, supersampling=2, out=background.copy())
    noise = np.random.default_rng(3).normal(0, 0.002 * 2 * r_big * abs(C), data.shape)
    return (Scan(data=(data + noise).astype(np.float32), geometry=g, background=background.astype(np.float32),
                 bubble_contrast=C), centres, axes, rot, half)


@pytest.fixture(scope="module")
def case():
    return _scan()


def test_each_small_bubble_and_cap_gets_one_initial_bubble(case):
    from bubsub.core import MeshProjector
    from bubsub.clients.pipeline.reconstruct import initial_bubbles

    scan, centres, axes, _, _ = case
    surfaces, _, image, extent, finer = initial_bubbles(scan.bubble_data, scan.geometry, scan.bubble_contrast,
                                                        MeshProjector(scan.geometry),
                                                        ReconstructionSettings(progress=False))
    assert finer is None and (extent[1] - extent[0]) / image.shape[-1] == pytest.approx(2.4 * PX)
    seeds = np.array([s.fine().centroid for s in surfaces])
    holds = np.linalg.norm(seeds[None] - centres[:, None], axis=2) < axes[:, :1]  # (truth, seed)
    # the distance maxima of the opened Otsu mask alone seed none of the four small balls
    assert holds.sum(axis=1).tolist() == [1] * len(centres) and holds.sum() == len(seeds)


def test_small_bubbles_and_edge_caps_are_each_found(case):
    scan, centres, axes, rot, half = case
    rec = reconstruct(scan, ReconstructionSettings(progress=False))
    # scored on one-pixel voxels over the bubbles' square, between the detector's top and bottom planes
    n_xy = int(round(2.8 / PX))
    shape, extent = (32, n_xy, n_xy), (-1.4, 1.4, -1.4, 1.4, -half, half)
    truth = ellipsoid_labels(centres, axes, rot, shape, extent)
    scores = match(truth, label_image([s.fine() for s in rec.surfaces], shape, extent))
    assert scores["truth"] == len(centres)
    assert scores["found"] == len(centres), scores["per_truth"]
    assert scores["spurious"] == 0 and scores["merged"] == 0
    assert scores["median_iou"] > 0.7
