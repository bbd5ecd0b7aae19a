"""bubsub.core.analysis.shape: size and shape of subdivided meshes against analytic spheres and ellipsoids."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bubsub.bench.analysis_truth import ellipsoid_area, subdivided_ellipsoid
from bubsub.core.analysis.shape import bubble_shape, solid_moments, strain_from_axes
from bubsub.core.projection.subdivision import sphere_surface

AXES = np.array([0.6, 0.45, 0.3])
ROT = Rotation.from_euler("zyx", [30, 50, -20], degrees=True).as_matrix()


def test_sphere_volume_area_and_sphericity_converge_to_the_ball():
    R = 0.7
    errors, sphericity = [], []
    for levels in (2, 3):
        s = bubble_shape(sphere_surface((0.3, -0.2, 1.0), R, -0.1, levels=levels).fine())
        errors.append((s["volume_mm3"] / (4 / 3 * np.pi * R ** 3) - 1, s["surface_area_mm2"] / (4 * np.pi * R * R) - 1))
        assert s["equivalent_diameter_mm"] == pytest.approx(np.cbrt(6 * s["volume_mm3"] / np.pi))
        assert [s["centroid_x_mm"], s["centroid_y_mm"], s["centroid_z_mm"]] == pytest.approx([0.3, -0.2, 1.0], abs=1e-12)
        assert s["strain_von_mises"] < 1e-6
        # the Loop limit of a 42-vertex icosphere is a ball to within 3e-4 in sphericity
        assert s["sphericity"] == pytest.approx(1.0, abs=3e-4)
        assert s["sphericity_ellipsoid"] == pytest.approx(1.0, abs=1e-5)
        sphericity.append(s["sphericity"])
    # both levels are estimates of one limit surface: the faceting (3x larger at level 2 than at 3) is gone
    assert sphericity[0] == pytest.approx(sphericity[1], abs=2e-5)
    (v2, a2), (v3, a3) = errors
    assert abs(v2) < 0.01
    # faceting error of the polyhedron's volume: second order in the edge length, a quarter per level
    assert 3 < v2 / v3 < 5
    # the area is the smooth surface's at the polyhedron's volume: about a ball's, (1 + v)^(2/3)
    for v, a in errors:
        assert a == pytest.approx((1 + v) ** (2 / 3) - 1, abs=3e-4)


def test_smooth_surface_sphericity_removes_the_facets_error():
    mesh = subdivided_ellipsoid(AXES, ROT, np.zeros(3), 1, 2)
    V, A = 4 / 3 * np.pi * AXES.prod(), ellipsoid_area(AXES)
    truth = np.pi ** (1 / 3) * (6 * V) ** (2 / 3) / A
    faceted = np.pi ** (1 / 3) * (6 * mesh.volume) ** (2 / 3) / mesh.area  # the 642-vertex polyhedron's own
    s = bubble_shape(mesh)
    assert abs(faceted - truth) > 5e-4
    assert abs(s["sphericity"] - truth) < abs(faceted - truth) / 20
    assert s["sphericity"] == pytest.approx(np.pi ** (1 / 3) * (6 * s["volume_mm3"]) ** (2 / 3) / s["surface_area_mm2"])


def test_ellipsoid_sphericity_is_foamquants_thomsen_formula():
    # FoamQuant RegionProp: volume 4/3 pi a b c, area 4 pi ((a^p b^p + a^p c^p + b^p c^p) / 3)^(1/p), p = 1.6
    a, b, c = AXES
    p = 1.6
    thomsen = 4 * np.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)
    expected = np.pi ** (1 / 3) * (6 * 4 / 3 * np.pi * a * b * c) ** (2 / 3) / thomsen
    s = bubble_shape(subdivided_ellipsoid(AXES, ROT, np.zeros(3), 1, 3))
    assert s["sphericity_ellipsoid"] == pytest.approx(expected, abs=2e-4)
    # Thomsen's formula is within about 1 % of the exact area
    assert thomsen == pytest.approx(ellipsoid_area(AXES), rel=0.012)


def test_ellipsoid_volume_area_shape_tensor_and_strain_against_the_analytic_values():
    centre = np.array([1.0, -2.0, 0.5])
    V, A = 4 / 3 * np.pi * AXES.prod(), ellipsoid_area(AXES)
    truth_sph = np.pi ** (1 / 3) * (6 * V) ** (2 / 3) / A
    truth_u, truth_vm, truth_kind = strain_from_axes(AXES)
    errs = []
    for control, levels in ((1, 2), (1, 3)):
        s = bubble_shape(subdivided_ellipsoid(AXES, ROT, centre, control, levels))
        errs.append(s["volume_mm3"] / V - 1)
        assert s["volume_mm3"] == pytest.approx(V, rel=0.01)
        assert s["surface_area_mm2"] == pytest.approx(A, rel=0.006)
        assert s["sphericity"] == pytest.approx(truth_sph, abs=1e-4)
        assert [s[f"centroid_{a}_mm"] for a in "xyz"] == pytest.approx(centre, abs=1e-9)
        # shape tensor: eigenvalues a_i^2 / 5 along the rotated axes
        assert [s[f"semi_axis_{i}_mm"] for i in (1, 2, 3)] == pytest.approx(AXES, rel=0.004)
        for i in range(3):
            axis = np.array([s[f"axis_{i + 1}_{a}"] for a in "xyz"])
            assert abs(axis @ ROT[:, i]) == pytest.approx(1.0, abs=1e-9)
        assert [s[f"strain_{i}"] for i in (1, 2, 3)] == pytest.approx(truth_u, abs=1e-3)
        assert s["strain_von_mises"] == pytest.approx(truth_vm, abs=1e-3)
        assert s["shape_type"] == truth_kind == 1  # 0.6 : 0.45 : 0.3 departs most along the shortest axis
    assert 3 < errs[0] / errs[1] < 5


def test_moments_of_a_box_mesh_are_exact():
    lx, ly, lz = 2.0, 1.0, 0.5
    v = np.array([[x, y, z] for x in (0, lx) for y in (0, ly) for z in (0, lz)], dtype=float) + [5, -3, 2]
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    vol, c, M = solid_moments(v, f)
    assert vol == pytest.approx(lx * ly * lz)
    assert c == pytest.approx([5 + lx / 2, -3 + ly / 2, 2 + lz / 2])
    assert M / vol == pytest.approx(np.diag([lx ** 2, ly ** 2, lz ** 2]) / 12, abs=1e-12)


def test_oblate_and_prolate_types():
    _, _, kind = strain_from_axes(np.array([[1.0, 1.0, 0.5], [1.0, 0.5, 0.5]]))
    assert kind.tolist() == [1, -1]
