"""Track ids after a warm subscan's detection: which fitted bubble that became two is a coalescence (3D).

:func:`~bubsub.clients.pipeline.dynamic4d.tracks.assign_tracks` on constructed scenes: one warm-fitted bubble
(the successor's track 7) over two bubbles found in it, the successor's bubble as large as the two together,
so that their sizes alone call it a coalescence.
"""

import numpy as np
import pytest

from bubsub.core import ScanGeometry, sphere_surface
from bubsub.clients.pipeline.dynamic4d.tracks import COALESCENCE_SHARE, assign_tracks, coalesces, edge_side

CONTRAST = -0.1
#: 32 rows of 0.05 mm: the field of view's top and bottom planes at z = +-0.8 mm.
GEOMETRY = ScanGeometry.parallel(np.linspace(0, np.pi, 24, endpoint=False), pixel_size=0.05, cols=64, rows=32)


def volume(r):
    return 4 / 3 * np.pi * r ** 3


def tracks(big, small, z_big, z_small):
    """assign_tracks on a warm fit covering a bubble of radius ``big`` and one of ``small`` beside it."""
    a = sphere_surface((-0.15, 0.0, z_big), big, CONTRAST)
    b = sphere_surface((0.15 + big, 0.0, z_small), small, CONTRAST)
    cover = sphere_surface((0.15 * small / big, 0.0, 0.5 * (z_big + z_small)), 2.2 * big, CONTRAST)
    ids, lineage, next_id = assign_tracks([7, 8], [cover, sphere_surface((0.0, 1.5, 0.0), 0.2, CONTRAST)], [a, b],
                                          {7: volume(big) + volume(small), 8: volume(0.2)}, GEOMETRY, next_id=20)
    return (a, b), ids, lineage, next_id


def test_a_cap_at_the_top_edge_beside_a_cut_neighbour_is_no_coalescence():
    # a neighbour cut by the top plane (z 0.25..0.95) and a cap beyond it (0.72..1.12): the visible parts'
    # shares would pass the size test, the edge does not
    (a, b), ids, lineage, next_id = tracks(0.35, 0.2, 0.6, 0.92)
    assert edge_side(a, GEOMETRY) == edge_side(b, GEOMETRY) == "top"
    assert volume(0.2) / (volume(0.35) + volume(0.2)) > COALESCENCE_SHARE
    assert not lineage["coalescences"] and ids == [7, 20] and next_id == 21
    assert "split off bubble 7" in lineage["new"][20] and "top edge" in lineage["new"][20]


def test_two_comparable_bubbles_inside_the_field_of_view_are_a_coalescence():
    (a, b), ids, lineage, next_id = tracks(0.3, 0.22, 0.0, 0.05)
    assert edge_side(a, GEOMETRY) is None and edge_side(b, GEOMETRY) is None
    assert lineage["coalescences"] == [{"parent": 7, "children": [20, 21]}] and ids == [20, 21] and next_id == 22
    assert not lineage["new"]


def test_a_small_bubble_beside_a_swollen_neighbour_is_no_coalescence():
    # inside the field of view, but a tenth of the pair's volume: a bubble whose space the warm fit took
    (a, b), ids, lineage, _ = tracks(0.35, 0.16, 0.0, 0.05)
    assert volume(0.16) / (volume(0.35) + volume(0.16)) < COALESCENCE_SHARE
    assert not lineage["coalescences"] and ids == [7, 20]
    assert lineage["new"][20] == "split off bubble 7, whose warm fit covered it"


@pytest.mark.parametrize("sizes, sides, known, expected", [
    ((1.0, 0.5), (None, None), 1.5, True),
    ((1.0, 0.5), (None, None), 1.1, False),  # the successor's bubble is about the larger alone
    ((1.0, 0.5), (None, "bottom"), 1.5, False),
    ((1.0, 0.1), (None, None), 1.1, False),
    ((1.0, 0.5), (None, None), None, False),
])
def test_coalesces_rule(sizes, sides, known, expected):
    assert coalesces(sizes, sides, known) is expected
