import numpy as np
import pytest

from bubsub.core import (
    Mesh,
    SubdivisionSurface,
    circle_surface,
    curve_subdivision,
    icosphere,
    loop_subdivision,
    sphere_mesh,
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


def test_surfaces_with_one_connectivity_share_a_topology():
    a = sphere_surface((0, 0, 0), 1.0, 0.5, control=42, levels=2)
    b = sphere_surface((3, 0, 0), 2.0, 0.5, control=42, levels=2)
    c = sphere_surface((0, 0, 0), 1.0, 0.5, control=42, levels=1)
    assert a.S is b.S and a.S is not c.S
    # shared, S must not change its summation order after the fact (scipy sorts indices in place)
    assert a.S.has_canonical_format and c.S.has_canonical_format
    _, f = icosphere(1)
    assert loop_subdivision(f, 42, 2)[0].has_canonical_format and curve_subdivision(9, 3).has_canonical_format
    assert circle_surface((0, 0), 1.0, 0.5, control=9, levels=2).S is circle_surface((1, 1), 2.0, 0.5, control=9, levels=2).S


@pytest.mark.parametrize("ndim", [2, 3])
def test_batched_subdivision_matches_one_product_per_surface(ndim):
    from bubsub.core.projection.subdivision import control_gradients, fine_vertices

    rng = np.random.default_rng(3)
    if ndim == 3:
        items = [sphere_surface(rng.uniform(-3, 3, 3), 1.0, 0.5, control=42, levels=lv) for lv in (2, 1, 2, 2, 1)]
        items.insert(2, sphere_mesh((5, 5, 5), 1.0, 0.5, subdivisions=1))  # a plain mesh among them
    else:
        items = [circle_surface(rng.uniform(-3, 3, 2), 1.0, 0.5, control=n, levels=2) for n in (9, 9, 12, 9)]
    items = [s.with_vertices(s.vertices + rng.normal(0, 0.05, s.vertices.shape)) if hasattr(s, "S") else s
             for s in items]
    fine = fine_vertices(items)
    grads = [rng.normal(size=f.shape) for f in fine]
    back = control_gradients(items, grads)
    for it, f, g, b in zip(items, fine, grads, back):
        S = getattr(it, "S", None)
        np.testing.assert_allclose(f, S @ it.vertices if S is not None else it.vertices, rtol=0, atol=1e-13)
        np.testing.assert_allclose(b, S.T @ g if S is not None else g, rtol=0, atol=1e-12)
        assert b.shape == it.vertices.shape


def test_subdivision_products_split_among_threads_are_the_serial_ones(monkeypatch):
    """The sparse products through S, split by surfaces among threads, give the one product's
    numbers to the bit, for every item and whatever the mix of topologies and meshes."""
    from bubsub.core.projection import subdivision
    from bubsub.core.projection.subdivision import control_gradients, fine_vertices

    rng = np.random.default_rng(5)
    items = [sphere_surface(rng.normal(size=3), 0.3 + 0.1 * k, 0.2, levels=2) for k in range(5)]
    items.insert(2, Mesh(*icosphere(1), 0.3))  # a plain mesh among them
    items += [sphere_surface(rng.normal(size=3), 0.4, 0.2, control=12, levels=1) for _ in range(3)]
    serial = fine_vertices(items)
    grads = [rng.normal(size=v.shape) for v in serial]
    serial_grads = control_gradients(items, grads)
    monkeypatch.setattr(subdivision, "THREADED_FINE_VERTICES", 0)
    assert len(subdivision._split(items, 3)) == 6  # 3 parts per topology
    for a, b in zip(fine_vertices(items, threads=3), serial):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(control_gradients(items, grads, threads=3), serial_grads):
        np.testing.assert_array_equal(a, b)
