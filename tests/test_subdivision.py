import numpy as np
import pytest

from bubsub.core import (
    Mesh,
    SubdivisionSurface,
    circle_surface,
    curve_subdivision,
    icosphere,
    loop_subdivision,
    sphere_surface,
)


@pytest.mark.parametrize("subdivisions, n", [(0, 12), (1, 42), (2, 162)])
def test_icosphere_sizes_and_closed(subdivisions, n):
    v, f = icosphere(subdivisions)
    assert v.shape == (n, 3)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0)
    assert Mesh(v, f).volume > 0  # validation: closed and outward


@pytest.mark.parametrize("levels", [0, 1, 2, 3])
def test_loop_matrix_is_affine_and_sizes_grow(levels):
    v, f = icosphere(0)
    S, fine = loop_subdivision(f, len(v), levels)
    assert fine.shape == (20 * 4**levels, 3)
    n_fine = {0: 12, 1: 42, 2: 162, 3: 642}[levels]
    assert S.shape == (n_fine, 12)
    np.testing.assert_allclose(np.asarray(S.sum(axis=1)).ravel(), 1.0)  # affine invariance
    shift = np.array([1.0, -2.0, 3.0])
    np.testing.assert_allclose(S @ (v + shift), S @ v + shift, atol=1e-12)
    Mesh(S @ v, fine)  # the fine mesh is closed and consistently oriented


def test_loop_weights_match_the_scheme():
    # One step on an icosahedron: valence 5, beta = (5/8 - (3/8 + cos(2pi/5)/4)^2) / 5
    v, f = icosphere(0)
    S, _ = loop_subdivision(f, 12, 1)
    beta = (5 / 8 - (3 / 8 + np.cos(2 * np.pi / 5) / 4) ** 2) / 5
    row0 = S[0].toarray().ravel()
    assert row0[0] == pytest.approx(1 - 5 * beta)
    assert np.count_nonzero(row0) == 6 and np.allclose(row0[row0 > 0][row0[row0 > 0] != row0[0]], beta)
    edge_rows = S[12:].toarray()
    assert np.allclose(np.sort(edge_rows, axis=1)[:, -4:], [1 / 8, 1 / 8, 3 / 8, 3 / 8])


def test_curve_subdivision_weights_and_orientation():
    S = curve_subdivision(5, 1).toarray()
    assert S.shape == (10, 5)
    np.testing.assert_allclose(S[0], [6 / 8, 1 / 8, 0, 0, 1 / 8])
    np.testing.assert_allclose(S[1], [0.5, 0.5, 0, 0, 0])
    assert curve_subdivision(7, 3).shape == (56, 7)


def test_sphere_and_circle_surfaces_have_the_requested_radius():
    s = sphere_surface([1, 2, 3], 0.8, -0.1)
    fine = s.fine()
    assert len(s.vertices) == 42 and len(fine.vertices) == 642
    r = np.linalg.norm(fine.vertices - [1, 2, 3], axis=1)
    assert r.mean() == pytest.approx(0.8, rel=1e-9) and r.std() < 0.02 * 0.8
    c = circle_surface([0.5, -0.5], 1.2, -0.1, control=9)
    pf = c.fine()
    assert len(pf.vertices) == 36
    assert np.linalg.norm(pf.vertices - [0.5, -0.5], axis=1).mean() == pytest.approx(1.2)
    assert pf.area == pytest.approx(np.pi * 1.2**2, rel=0.02)


def test_surface_with_vertices_shares_the_matrix():
    s = sphere_surface([0, 0, 0], 1.0, -0.1)
    s2 = s.with_vertices(s.vertices * 2)
    assert s2.S is s.S
    np.testing.assert_allclose(s2.fine().vertices, 2 * s.fine().vertices)
    with pytest.raises(TypeError):
        SubdivisionSurface(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="levels"):
        SubdivisionSurface(s.control, levels=-1)
