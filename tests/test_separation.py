"""The separation penalty: zero for bubbles a film apart, its gradient, and fits that keep the film."""

import numpy as np
import pytest

from bubsub.clients.optimise.separation import separation_penalty
from bubsub.core import circle_surface, sphere_surface


def _fd(vertex_sets, weight, gap, eps=1e-6):
    out = []
    for k, v in enumerate(vertex_sets):
        g = np.zeros_like(v)
        for idx in np.ndindex(v.shape):
            plus = [w.copy() for w in vertex_sets]
            minus = [w.copy() for w in vertex_sets]
            plus[k][idx] += eps
            minus[k][idx] -= eps
            g[idx] = (separation_penalty(plus, weight, gap)[0] - separation_penalty(minus, weight, gap)[0]) / (2 * eps)
        out.append(g)
    return out


@pytest.mark.parametrize("make, shift", [(circle_surface, [0.9, 0.2]), (sphere_surface, [0.85, 0.1, -0.2])])
def test_penalty_gradient_matches_finite_differences(make, shift):
    rng = np.random.default_rng(1)
    a = make(np.zeros(len(shift)), 0.5, -0.1).vertices + 0.02 * rng.standard_normal((1, len(shift)))
    b = make(np.array(shift), 0.45, -0.1).vertices
    b = b + 0.03 * rng.standard_normal(b.shape)
    value, grads = separation_penalty([a, b], weight=3.0, gap=0.05)
    assert value > 0
    for g, fd in zip(grads, _fd([a, b], 3.0, 0.05)):
        np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-7)


def test_penalty_is_zero_exactly_when_a_plane_leaves_the_film():
    a = circle_surface([0, 0], 0.5, -0.1).vertices
    right = a[:, 0].max()
    b = a + [right + 0.1 - a[:, 0].min(), 0]  # control vertices 0.1 mm apart along x
    assert separation_penalty([a, b], 1.0, gap=0.09)[0] == 0
    # a film of 0.12 needs the extreme vertices (p on one side, q on the other) moved 0.02 mm in all,
    # shared so that the squared moves are least: 0.5 * 0.02^2 * p q / (p + q)
    p, q = np.sum(np.isclose(a[:, 0], right)), np.sum(np.isclose(b[:, 0], b[:, 0].min()))
    assert (p, q) == (1, 2)  # a 9-gon: one vertex at 0 degrees, two at +-160
    assert separation_penalty([a, b], 1.0, gap=0.12)[0] == pytest.approx(0.5 * 0.02**2 * p * q / (p + q), rel=1e-6)


def test_fit_with_the_penalty_keeps_bubbles_apart_where_the_data_favour_an_overlap():
    from bubsub.clients.optimise.fit import fit
    from bubsub.clients.optimise.separation import separation_weight
    from bubsub.core import MeshProjector, ScanGeometry
    from bubsub.core.projection.validity import check_bubbles

    # projections of two discs that share 0.1 mm of gas (counted twice): the projection distance
    # alone is least with the overlap, the penalty must keep the two a film apart
    truth = [circle_surface([-0.45, 0.0], 0.5, -0.1, control=32, levels=3),
             circle_surface([0.45, 0.0], 0.5, -0.1, control=32, levels=3)]
    geometry = ScanGeometry.parallel(np.linspace(0, np.pi, 6, endpoint=False), cols=96, pixel_size=0.03)
    projector = MeshProjector(geometry)
    data = projector.forward(truth)
    start = [circle_surface([-0.55, 0.02], 0.45, -0.1), circle_surface([0.55, -0.02], 0.45, -0.1)]
    assert check_bubbles(start) == []
    free = fit(projector, start, data, iterations=40, progress=False)
    assert [v.kind for v in check_bubbles(free.surfaces)] == ["overlap"]
    w = separation_weight(data, 2, voxel=0.03)
    res = fit(projector, start, data, iterations=40, progress=False,
              penalty=lambda v: separation_penalty(v, w, gap=0.01))
    assert check_bubbles(res.surfaces) == []
    assert 0 < res.penalty < res.objective  # a penalty, not a hard constraint: the data still pull a little
