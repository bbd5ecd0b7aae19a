import numpy as np
import pytest

from bubsub.core import Mesh, Polygon, icosphere


def unit_cube():
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, f


def test_cube_volume_area_centroid():
    v, f = unit_cube()
    m = Mesh(v * 2 + 1, f, 0.3)
    assert m.volume == pytest.approx(8.0)
    assert m.area == pytest.approx(24.0)
    np.testing.assert_allclose(m.centroid, [2, 2, 2])


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda v, f: (np.where(np.arange(v.size).reshape(v.shape) == 4, np.nan, v), f), "NaN or inf"),
        (lambda v, f: (v, np.where(f == 7, 8, f)), "out of range"),
        (lambda v, f: (v, f[:-1]), "not closed"),
        (lambda v, f: (v, np.vstack([f[:-1], f[-1:, ::-1]])), "consistently oriented"),
        (lambda v, f: (v, f[:, ::-1]), "inwards"),
        (lambda v, f: (v, np.vstack([f[:-1], [[1, 1, 3]]])), "degenerate"),
        (lambda v, f: (v[:, :2], f), "shape"),
        (lambda v, f: (v, f.astype(float) + 0.5), "integer"),
    ],
)
def test_invalid_meshes_are_refused_with_a_named_reason(mutate, message):
    v, f = unit_cube()
    v2, f2 = mutate(v, f)
    with pytest.raises(ValueError, match=message):
        Mesh(v2, f2)


def test_with_vertices_keeps_topology_and_checks_values():
    v, f = icosphere(1)
    m = Mesh(v, f, -0.1)
    m2 = m.with_vertices(v * 2)
    assert m2.faces is m.faces and m2.attenuation == -0.1
    assert m2.volume == pytest.approx(8 * m.volume)
    with pytest.raises(ValueError, match="NaN"):
        m.with_vertices(np.full_like(v, np.inf))
    with pytest.raises(ValueError, match="shape"):
        m.with_vertices(v[:-1])


def test_polygon_measures_and_orientation():
    sq = np.array([[0, 0], [2, 0], [2, 1], [0, 1]], float)
    p = Polygon(sq, 0.1)
    assert p.area == pytest.approx(2.0)
    assert p.perimeter == pytest.approx(6.0)
    np.testing.assert_allclose(p.centroid, [1, 0.5])
    with pytest.raises(ValueError, match="clockwise"):
        Polygon(sq[::-1])
    with pytest.raises(ValueError, match="at least 3"):
        Polygon(sq[:2])
    with pytest.raises(ValueError, match="attenuation"):
        Polygon(sq, float("nan"))


def test_equivalent_radius_and_size_of_meshes_and_polygons():
    from bubsub.core.projection.mesh import equivalent_radius

    v, f = unit_cube()
    cube = Mesh(v * 2, f)  # volume 8: the ball of volume 8 has radius (6 / pi)^(1/3)
    assert cube.size == cube.volume == pytest.approx(8.0)
    assert cube.equivalent_radius == pytest.approx((6 / np.pi) ** (1 / 3))
    square = Polygon([[0, 0], [3, 0], [3, 3], [0, 3]])  # area 9: the disc of area 9 has radius 3 / sqrt(pi)
    assert square.size == square.area == pytest.approx(9.0)
    assert square.equivalent_radius == pytest.approx(3 / np.sqrt(np.pi))
    inside_out = square.with_vertices(square.vertices[::-1])  # a fit may turn a bubble clockwise
    assert inside_out.size == pytest.approx(-9.0) and inside_out.equivalent_radius == 0.0
    np.testing.assert_allclose(equivalent_radius(np.array([4 / 3 * np.pi, -1.0]), 3), [1.0, 0.0])


def test_mean_edge_of_a_regular_tetrahedron_and_a_square():
    v = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=float)  # every edge 2 sqrt(2)
    f = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    assert Mesh(v, f).mean_edge == pytest.approx(2 * np.sqrt(2))
    assert Polygon(np.array([[0, 0], [2, 0], [2, 2], [0, 2]], dtype=float)).mean_edge == pytest.approx(2.0)
