"""A warm-started bubble that keeps only a sliver less deep than two detector rows in view ends its track (3D).

The data are projected from icospheres (not the fitted subdivision model) with Gaussian noise of a fixed seed.
"""

import numpy as np
import pytest
import trimesh

from bubsub.core import MeshProjector, ScanGeometry, sphere_surface
from bubsub.core.io.scanfile import Scan
from bubsub.core.projection.mesh import Mesh
from bubsub.clients.pipeline.dynamic4d.chain import (MIN_EDGE_ROWS, BubbleState, DynamicSettings, edge_depth,
                                                     reconstruct_subscan)

CONTRAST = -0.1
GEOMETRY = ScanGeometry.parallel(np.linspace(0, np.pi, 16, endpoint=False), pixel_size=0.1, cols=32, rows=24)
HALF = 1.2  # the field of view's half height: 24 rows of 0.1 mm


def ball(centre, radius):
    m = trimesh.creation.icosphere(subdivisions=3)
    return Mesh(np.asarray(m.vertices) * radius + np.asarray(centre), np.asarray(m.faces), CONTRAST)


@pytest.mark.parametrize("z, depth", [(-1.5, 0.1), (1.4, 0.2), (0.0, np.inf), (-1.0, 0.6)])
def test_edge_depth_is_how_deep_a_cut_bubble_reaches_into_view(z, depth):
    s = sphere_surface((0.0, 0.0, z), 0.4, CONTRAST, control=42, levels=3)
    assert edge_depth(s, GEOMETRY) == pytest.approx(depth, abs=0.01)


def test_a_bubble_whose_part_in_view_is_a_sliver_ends_its_track_and_a_cap_stays():
    truth = {"A": ((-0.5, 0.0, 0.0), 0.45), "C": ((0.5, 0.3, 1.45), 0.5)}  # C: a cap 0.25 mm (2.5 rows) deep
    data = MeshProjector(GEOMETRY).forward([ball(*x) for x in truth.values()])
    data = (data + np.random.default_rng(4).normal(0, 0.002, data.shape)).astype(np.float32)
    scan = Scan(data=data, geometry=GEOMETRY, bubble_contrast=CONTRAST)
    # the successor's bubble S reached 0.3 mm into view at the bottom; it has left since (no gas there now)
    successor = BubbleState.from_surfaces([0, 1, 2], [sphere_surface(truth["A"][0], 0.45, CONTRAST),
                                                      sphere_surface((0.5, 0.3, 1.45), 0.5, CONTRAST),
                                                      sphere_surface((-0.4, -0.5, -1.55), 0.5, CONTRAST)])
    res = reconstruct_subscan(scan, successor, DynamicSettings(iterations=20, progress=False, detect=False),
                              index=2, time=2.0)
    assert set(res.state.ids) == {0, 1}
    assert res.ended == (2,) and "left the field of view" in res.report["ended"]["2"]
    cap = dict(zip(res.state.ids, res.state.surfaces()))[1]
    assert edge_depth(cap, GEOMETRY) >= MIN_EDGE_ROWS * 0.1
