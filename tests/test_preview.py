"""The voxel preview's grid follows the bubbles when they are only a few of its voxels across."""

import numpy as np
import pytest

from bubsub.core.foam.ellipsoids import project_ellipsoids
from bubsub.core.io.scanfile import Scan
from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.projection.subdivision import sphere_surface
from bubsub.clients.pipeline.static import preview
from bubsub.clients.pipeline.static.preview import (BUBBLE_VOXELS, preview_grid, preview_voxel_size, voxel_for_bubbles)
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, reconstruct

C = -0.1
PIXEL = 0.00625
# 20 parallel views of a 320 x 32 detector: field of view 2 mm across, default preview voxel 0.0125 mm (2 pixels)
GEOMETRY = ScanGeometry.parallel(np.linspace(0, np.pi, 20, endpoint=False), pixel_size=PIXEL, cols=320, rows=32)


def test_the_voxel_puts_the_asked_voxels_across_the_median_bubble_no_finer_than_a_pixel():
    voxel = preview_voxel_size(GEOMETRY)
    assert voxel == pytest.approx(2 * PIXEL)
    across = lambda d: np.full(9, d * voxel / 2)  # radii of bubbles d voxels across
    assert voxel_for_bubbles(across(6.4), GEOMETRY, voxel) == pytest.approx(voxel * 6.4 / BUBBLE_VOXELS)
    assert voxel_for_bubbles(np.r_[across(6.4), across(100)[:4]], GEOMETRY, voxel) == \
        pytest.approx(voxel * 6.4 / BUBBLE_VOXELS)  # the median, not the mean
    assert voxel_for_bubbles(across(7.2), GEOMETRY, voxel) is None  # wide enough already
    assert voxel_for_bubbles(across(3.0), GEOMETRY, voxel) == pytest.approx(PIXEL)  # the detector's own limit
    assert voxel_for_bubbles([], GEOMETRY, voxel) is None
    assert voxel_for_bubbles([np.nan, -1.0, 0.0], GEOMETRY, voxel) is None


def test_the_finer_grid_stays_within_the_voxel_budget(monkeypatch):
    voxel = preview_voxel_size(GEOMETRY)
    radii = np.full(5, 3.0 * voxel / 2)
    free = voxel_for_bubbles(radii, GEOMETRY, voxel)
    budget = np.prod(preview_grid(GEOMETRY, voxel).shape) * 2  # twice the default grid's voxels
    monkeypatch.setattr(preview, "MAX_PREVIEW_VOXELS", budget)
    capped = voxel_for_bubbles(radii, GEOMETRY, voxel)
    assert free < capped < voxel
    assert np.prod(preview_grid(GEOMETRY, capped).shape) <= 1.1 * budget
    monkeypatch.setattr(preview, "MAX_PREVIEW_VOXELS", np.prod(preview_grid(GEOMETRY, voxel).shape))
    assert voxel_for_bubbles(radii, GEOMETRY, voxel) is None  # no finer grid fits: the default stays


def _packed_bubbles():
    """72 balls of radius 0.033 mm (5.3 default voxels across) in two layers, films of a quarter pixel."""
    r, film = 0.033, 0.0015
    step = 2 * r + film
    xs = (np.arange(6) - 2.5) * step
    centres = np.array([[x, y + 0.5 * step * k, z] for k, z in enumerate((-(r + film / 2), r + film / 2))
                        for x in xs for y in xs])
    data = project_ellipsoids(GEOMETRY, centres, np.full((len(centres), 3), r), np.stack([np.eye(3)] * len(centres)),
                              C, supersampling=2)
    return Scan(data, GEOMETRY, bubble_contrast=C), centres, r


QUICK = dict(iterations=2, data_levels=1, topology=False, refine=False, repair=False, estimate_radii=False)


def test_touching_bubbles_few_voxels_across_are_seeded_one_by_one_and_get_the_finer_preview():
    scan, centres, r = _packed_bubbles()
    default = reconstruct(scan, ReconstructionSettings(voxel_size=preview_voxel_size(GEOMETRY), **QUICK))
    assert default.report["preview"]["finer_for_bubbles"] is False
    # touching balls fuse into chains in the distance transform's opened mask; the small blobs seeded beside
    # it (blobs.small_blobs) give each its seed even at the default voxel
    assert default.report["bubbles_initial"] == len(centres)
    rec = reconstruct(scan, ReconstructionSettings(**QUICK))
    p = rec.report["preview"]
    assert p["finer_for_bubbles"] is True and p["voxel_mm"] < preview_voxel_size(GEOMETRY)
    assert rec.preview.shape == tuple(p["shape"]) and rec.report["bubbles_initial"] == len(centres)
    found = np.array([s.fine().vertices.mean(axis=0) for s in rec.surfaces])
    nearest = np.linalg.norm(found[:, None] - centres[None], axis=2).argmin(axis=1)
    assert sorted(nearest) == list(range(len(centres)))  # one bubble per true ball
    assert np.linalg.norm(found - centres[nearest], axis=1).max() < r / 2
    assert set(rec.report["seconds_parts"]) >= {"preview", "initial_bubbles"}


def test_a_warm_start_of_small_bubbles_previews_at_the_voxel_their_size_asks_for():
    scan, centres, r = _packed_bubbles()
    init = [sphere_surface(c, r, attenuation=C) for c in centres]
    rec = reconstruct(scan, ReconstructionSettings(**QUICK), init=init)
    want = voxel_for_bubbles([s.fine().equivalent_radius for s in init], GEOMETRY, preview_voxel_size(GEOMETRY))
    assert rec.report["preview"]["finer_for_bubbles"] is True
    assert rec.report["preview"]["voxel_mm"] == pytest.approx(want, rel=0.02)
