"""Liquid containers (a square in 2D, a box in 3D) and sphere meshes for phantoms."""

from __future__ import annotations

import numpy as np

from bubsub.core.projection.mesh import Mesh, Polygon
from bubsub.core.foam.checks import unit_icosphere, positive, size_vector

__all__ = ['liquid_square', 'liquid_box', 'sphere_mesh']


def liquid_square(size=10.0, attenuation=0.1):
    """Square liquid container centred at the origin.

    Parameters
    ----------
    size : float
        Side length, mm.
    attenuation : float
        1/mm.

    Returns
    -------
    Polygon
        4 vertices, counter-clockwise.
    """
    h = positive("size", size) / 2.0
    return Polygon([[-h, -h], [h, -h], [h, h], [-h, h]], attenuation)


_BOX_FACES = np.array(
    [
        [0, 2, 1], [0, 3, 2],  # z min (normal -z)
        [4, 5, 6], [4, 6, 7],  # z max (+z)
        [0, 1, 5], [0, 5, 4],  # y min (-y)
        [3, 7, 6], [3, 6, 2],  # y max (+y)
        [0, 4, 7], [0, 7, 3],  # x min (-x)
        [1, 2, 6], [1, 6, 5],  # x max (+x)
    ]
)


def liquid_box(size=(20.0, 20.0, 10.0), attenuation=0.1):
    """Box-shaped liquid container centred at the origin.

    Parameters
    ----------
    size : (3,) float
        Side lengths (x, y, z), mm.
    attenuation : float
        1/mm.

    Returns
    -------
    Mesh
        8 vertices, 12 outward-oriented triangles.
    """
    s = size_vector(size, 3)
    hx, hy, hz = (v / 2.0 for v in s)
    verts = np.array(
        [
            [-hx, -hy, -hz], [hx, -hy, -hz], [hx, hy, -hz], [-hx, hy, -hz],
            [-hx, -hy, hz], [hx, -hy, hz], [hx, hy, hz], [-hx, hy, hz],
        ]
    )
    return Mesh(verts, _BOX_FACES, attenuation)


def sphere_mesh(centre, radius, attenuation, subdivisions=2):
    """Icosphere mesh of a sphere (``20 * 4**subdivisions`` triangles).

    Parameters
    ----------
    centre : (3,) float
    radius : float
    attenuation : float
    subdivisions : int
        2 gives 162 vertices and 320 triangles.

    Returns
    -------
    Mesh
    """
    unit_v, faces = unit_icosphere(subdivisions)
    c = np.asarray(centre, dtype=float)
    if c.shape != (3,):
        raise ValueError(f"centre must have shape (3,), got {c.shape}")
    return Mesh(c + positive("radius", radius) * unit_v, faces, attenuation)
