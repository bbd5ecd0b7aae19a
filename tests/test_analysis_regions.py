"""bubsub.core.analysis.regions: region volumes, gas shared among regions, texture, against closed forms."""

import numpy as np
import pytest

from bubsub.core.analysis.regions import Domain, region_volumes, texture_summary
from bubsub.core.analysis.snapshot import analyse_meshes
from bubsub.core.projection.mesh import Mesh
from bubsub.core.projection.subdivision import icosphere

V, F = icosphere(4)


def sphere(centre, radius):
    return Mesh(np.asarray(centre) + radius * V, F)


def test_region_volumes_of_a_cylinder_are_exact_quarters_and_annuli():
    dom = Domain.field_of_view(2.0, 1.0)
    cells, _, shells, _ = region_volumes([sphere((5.0, 0, 0), 0.3)], np.array([[5.0, 0, 0]]), dom, (2, 2, 1), 4)
    assert cells == pytest.approx(np.full(4, np.pi * 4 * 2 / 4), rel=2e-4)
    r = np.linspace(0, 2, 5)
    assert shells == pytest.approx(np.pi * np.diff(r ** 2) * 2, rel=1e-3)


def test_a_bubble_cut_by_a_cell_border_and_shells_is_shared_by_its_true_parts():
    R, x0 = 0.6, 0.2
    mesh = sphere((x0, 0.0, 0.0), R)
    dom = Domain((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    cells, gas, _, ring = region_volumes([mesh], np.array([[x0, 0, 0]]), dom, (2, 1, 1), 2)
    assert cells == pytest.approx([4.0, 4.0], rel=1e-9)
    assert gas.sum() == pytest.approx(mesh.volume, rel=1e-9)  # slices sum to the mesh's volume exactly
    scale = mesh.volume / (4 / 3 * np.pi * R ** 3)  # the mesh's own faceting, a fraction of a percent
    h = R - x0
    cap = np.pi * h * h * (3 * R - h) / 3  # the part at x < 0
    assert gas[0] == pytest.approx(cap * scale, rel=0.02)
    # a sphere centred on the axis: its part within r < 0.5 of the axis is a cylinder with two caps
    centred = sphere((0.0, 0.0, 0.0), R)
    shell_r = dom.outer_radius / 4  # 0.35 mm
    _, _, _, ring = region_volumes([centred], np.zeros((1, 3)), dom, (1, 1, 1), 4)
    inner = 4 * np.pi / 3 * (R ** 3 - (R * R - shell_r ** 2) ** 1.5)
    scale = centred.volume / (4 / 3 * np.pi * R ** 3)
    assert ring[0] == pytest.approx(inner * scale, rel=0.02)


def test_liquid_fraction_of_a_foam_and_the_part_inside_the_domain():
    # two bubbles inside a cylinder, one half outside its top: liquid = 1 - (gas inside) / cylinder
    meshes = [sphere((0.5, 0.0, 0.0), 0.4), sphere((-0.6, 0.3, 0.2), 0.35), sphere((0.0, -0.8, 1.0), 0.3)]
    snap = analyse_meshes(meshes, contact_gap=0.05, field_of_view=(1.5, 1.0), truncated=[0, 0, 1], grid=(1, 1, 1),
                          shells=1)
    gas = meshes[0].volume + meshes[1].volume + 0.5 * meshes[2].volume
    assert snap.summary["liquid_fraction"] == pytest.approx(1 - gas / (np.pi * 1.5 ** 2 * 2), abs=2e-4)
    assert snap.grid[0]["region_volume_mm3"] == pytest.approx(np.pi * 1.5 ** 2 * 2, rel=2e-4)


def test_texture_tensor_of_known_branch_vectors():
    b = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 2.0, 0], [0, 0, 0.5]])
    t, lam, u, vm = texture_summary(b)
    assert t == pytest.approx(np.diag([0.5, 1.0, 0.0625]))
    assert lam == pytest.approx([1.0, 0.5, 0.0625])
    g = np.cbrt(lam.prod())
    assert u == pytest.approx(0.5 * np.log(lam / g))
    assert vm == pytest.approx(np.sqrt(0.5 * ((u[0] - u[1]) ** 2 + (u[0] - u[2]) ** 2 + (u[1] - u[2]) ** 2)))
    empty = texture_summary(np.zeros((0, 3)))
    assert np.isnan(empty[0]).all() and np.isnan(empty[3])


def test_shell_texture_is_in_the_local_cylindrical_frame():
    # four pairs around the axis, each pair's branch vector radial: texture_rr carries everything
    meshes, r0 = [], 1.0
    for phi in np.radians([0, 90, 180, 270]):
        e = np.array([np.cos(phi), np.sin(phi), 0.0])
        meshes += [sphere(r0 * e, 0.2), sphere((r0 + 0.42) * e, 0.2)]
    snap = analyse_meshes(meshes, contact_gap=0.05, field_of_view=(2.0, 0.5), grid=(1, 1, 1), shells=1)
    assert len(snap.contacts) == 4
    row = snap.shells[0]
    assert row["texture_rr_mm2"] == pytest.approx(0.42 ** 2, rel=1e-6)
    assert abs(row["texture_phiphi_mm2"]) < 1e-12 and abs(row["texture_rphi_mm2"]) < 1e-12
    grid = snap.grid[0]  # in the Cartesian frame the same branches are half along x, half along y
    assert grid["texture_xx_mm2"] == pytest.approx(0.5 * 0.42 ** 2, rel=1e-6)
    assert grid["texture_yy_mm2"] == pytest.approx(0.5 * 0.42 ** 2, rel=1e-6)
