"""The 2D voxel preview on a detector of few columns: its voxels no finer than a pixel, one seed per bubble.

Truth: a random 2D foam (:func:`bubsub.core.foam.phantoms.foam2d`) rasterised
and projected by ASTRA with Poisson noise, not by the mesh projector the fit
uses. 60 views of 110 columns, 3000 photons: the field of view over 256
voxels would make voxels of 0.43 pixels, on which the box-constrained
preview is speckled and its Otsu mask breaks the bubbles into pieces.
"""

import numpy as np
import pytest

from bubsub.core.foam.phantoms import foam2d
from bubsub.core.foam.simulate import default_geometry_2d, simulate_2d
from bubsub.clients.pipeline.inputs.fov import field_of_view
from bubsub.clients.pipeline.static.initial import distance_centres
from bubsub.clients.pipeline.static.preview import preview_voxel_size, voxel_preview

PIXEL = 0.13  # mm: 110 columns cover the 10 mm square's diagonal
GEOMETRY = default_geometry_2d(60, det_count=110, pixel_size=PIXEL)


def test_a_2d_preview_voxel_is_no_finer_than_a_detector_pixel():
    assert 2 * field_of_view(GEOMETRY)[0] / 256 < 0.5 * PIXEL  # the field of view's 256 voxels: too fine
    assert preview_voxel_size(GEOMETRY) == pytest.approx(PIXEL)
    wide = default_geometry_2d(60, det_count=2400, pixel_size=0.006)
    assert preview_voxel_size(wide) == pytest.approx(2 * field_of_view(wide)[0] / 256)  # coarser than a pixel


@pytest.mark.parametrize("seed", [0, 2])
def test_each_bubble_gets_one_distance_seed_on_a_few_column_detector(seed):
    phantom = foam2d(seed, n_bubbles=12, radius_range=(0.4, 0.8))
    scan = simulate_2d(phantom, GEOMETRY, photons=3e3, seed=seed, image_size=1000)
    truth = np.array([b.centroid for b in phantom.bubbles])
    radii = np.array([b.equivalent_radius for b in phantom.bubbles])

    def seeds(voxel):
        image, extent = voxel_preview(scan.bubble_data, GEOMETRY, scan.bubble_contrast, voxel)
        return distance_centres(image, extent, border_is_background=False)[0]

    centres = seeds(preview_voxel_size(GEOMETRY))
    # every bubble holds exactly one seed, and every seed lies in a bubble
    owner = np.argmin(np.linalg.norm(centres[:, None] - truth[None], axis=2), axis=1)
    assert np.all(np.linalg.norm(centres - truth[owner], axis=1) < radii[owner])
    assert sorted(owner) == list(range(len(truth)))
    # the same data on the field of view's 256 voxels: the speckled preview seeds bubbles in pieces
    assert len(seeds(2 * field_of_view(GEOMETRY)[0] / 256)) > 1.5 * len(truth)
