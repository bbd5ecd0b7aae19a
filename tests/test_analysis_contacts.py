"""bubsub.core.analysis.contacts: closest-surface gaps of subdivided meshes against analytic ellipsoids."""

import functools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bubsub.bench.analysis_truth import ellipsoid_gap, subdivided_ellipsoid
from bubsub.core.analysis.contacts import Surface, find_contacts, surface_distance
from bubsub.core.projection.mesh import Mesh


def shape_matrix(axes, rotation):
    return rotation @ np.diag(np.asarray(axes) ** 2) @ rotation.T


def support(centre, A, n):
    """The point of the ellipsoid ``(x - c)^T A^-1 (x - c) <= 1`` farthest along the unit vector ``n``."""
    return centre + A @ n / np.sqrt(n @ A @ n)


def true_gap(c1, A1, c2, A2):
    """Distance between two disjoint ellipsoids, independently of any mesh (support planes)."""
    return ellipsoid_gap(c1, A1, c2, A2)[0]


def test_gap_between_two_ellipsoids_at_a_known_distance():
    rng = np.random.default_rng(1)
    for g in (0.01, 0.03, 0.05):
        ax1, ax2 = np.array([0.5, 0.4, 0.3]), np.array([0.45, 0.35, 0.3])
        R1, R2 = Rotation.random(2, random_state=rng).as_matrix()
        A1, A2 = shape_matrix(ax1, R1), shape_matrix(ax2, R2)
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        c1 = np.array([0.2, -0.1, 0.3])
        p1 = support(c1, A1, n)
        # the second ellipsoid touches the plane through p1 + g n from the far side: parallel support planes g apart
        c2 = p1 + g * n + A2 @ n / np.sqrt(n @ A2 @ n)
        assert true_gap(c1, A1, c2, A2) == pytest.approx(g, abs=1e-7)
        meshes = [subdivided_ellipsoid(ax1, R1, c1, levels=3), subdivided_ellipsoid(ax2, R2, c2, levels=3)]
        c = find_contacts(meshes, 0.06)
        assert c.pairs.tolist() == [[0, 1]]
        assert c.gap[0] == pytest.approx(g, abs=0.001)
        assert np.linalg.norm(c.point[0] - (p1 + 0.5 * g * n)) < 0.03
        assert c.film_area[0] > 0
        assert len(find_contacts(meshes, 0.9 * g)) == 0  # a gap just under the distance finds no contact


def test_overlapping_meshes_have_a_negative_gap_and_distances_are_signed():
    v, f = icosphere_mesh()
    a, b = Mesh(v * 0.5, f), Mesh(v * 0.4 + [0.85, 0, 0], f)
    c = find_contacts([a, b], 0.06)
    assert c.gap[0] == pytest.approx(-0.05, abs=0.002)  # the tip of b is 0.05 inside a
    d, q = surface_distance(np.array([[0.0, 0.0, 0.0], [0.55, 0.0, 0.0], [3.0, 0.0, 0.0]]), Surface.of(a), 0.6)
    assert d[0] == pytest.approx(-0.5, abs=0.002) and d[1] == pytest.approx(0.05, abs=0.002) and d[2] == np.inf
    assert np.isnan(q[2]).all() and np.linalg.norm(q[1] - [0.5, 0, 0]) < 0.01


def icosphere_mesh():
    from bubsub.core.projection.subdivision import icosphere

    return icosphere(4)


@functools.lru_cache(maxsize=None)  # built once for the tests that share it (read only)
def small_foam(seed, n=22, max_gap=0.12):
    """Ellipsoids each placed at a random gap in [0, max_gap] from an earlier one, disjoint from all (>= 5 um)."""
    rng = np.random.default_rng(seed)

    def draw():
        axes = 0.35 * np.exp(rng.normal(scale=0.12, size=3))
        return axes, Rotation.random(random_state=rng).as_matrix()

    axes, rot = draw()
    foam = [(np.zeros(3), axes, rot, shape_matrix(axes, rot))]
    while len(foam) < n:
        k = rng.integers(len(foam))
        axes, rot = draw()
        A = shape_matrix(axes, rot)
        nrm = rng.normal(size=3)
        nrm /= np.linalg.norm(nrm)
        g = rng.uniform(0.0, max_gap)
        c = support(foam[k][0], foam[k][3], nrm) + g * nrm + A @ nrm / np.sqrt(nrm @ A @ nrm)
        if all(np.linalg.norm(c - o[0]) > 1.2 or true_gap(o[0], o[3], c, A) > 0.005 for o in foam):
            foam.append((c, axes, rot, A))
    return foam


def test_contacts_precision_and_recall_against_the_true_surfaces():
    gap = 0.06
    foam = small_foam(7)
    truth = {}
    for i in range(len(foam)):
        for j in range(i + 1, len(foam)):
            if np.linalg.norm(foam[i][0] - foam[j][0]) < 1.2:
                truth[(i, j)] = true_gap(foam[i][0], foam[i][3], foam[j][0], foam[j][3])
    true_pairs = {p for p, g in truth.items() if g < gap}
    assert 10 <= len(true_pairs) <= len(truth) - 10  # the threshold cuts through the gaps
    # the meshes bubsub fits: 42 control vertices, two subdivision levels
    meshes = [subdivided_ellipsoid(axes, rot, c, control=1, levels=2) for c, axes, rot, _ in foam]
    c = find_contacts(meshes, gap)
    found = {tuple(p) for p in c.pairs.tolist()}
    hit = found & true_pairs
    assert len(hit) / len(found) >= 0.9 and len(hit) / len(true_pairs) >= 0.9
    for p, g in zip(c.pairs.tolist(), c.gap):
        assert g == pytest.approx(truth[tuple(p)], abs=0.004)  # a mesh lies within a few micrometres of its ellipsoid
    wrong = (found ^ true_pairs)
    assert all(abs(truth[p] - gap) < 0.004 for p in wrong)  # only pairs at the threshold itself may flip
    coordination = c.coordination(len(meshes))
    assert coordination.sum() == 2 * len(found)


def test_film_area_of_two_spheres_against_the_analytic_near_contact_caps():
    from bubsub.core.projection.subdivision import sphere_surface

    R, g0 = 0.5, 0.01
    D = 2 * R + g0
    a, b = sphere_surface((0, 0, 0), R, -0.1, levels=3).fine(), sphere_surface((D, 0, 0), R, -0.1, levels=3).fine()
    for gap in (0.06, 0.1):
        # a point of one sphere at polar angle t from the axis is within the gap of the other where
        # R^2 + D^2 - 2 R D cos t < (R + gap)^2: a cap of area 2 pi R^2 (1 - cos t0)
        cap = 2 * np.pi * R * R * (1 - (R * R + D * D - (R + gap) ** 2) / (2 * R * D))
        assert find_contacts([a, b], gap).film_area[0] == pytest.approx(cap, rel=0.1)
