"""bubsub.core: scan geometries, meshes, subdivision and the Embree mesh projector.

Units are millimetres and 1/mm; projections are float32 arrays with axes
``(angle, row, col)`` (3D) or ``(angle, col)`` (2D).
"""

from .geometry import ScanGeometry
from .mesh import Mesh, Polygon
from .projector import MeshProjector, Traversal
from .subdivision import (
    SubdivisionSurface,
    circle_surface,
    curve_subdivision,
    icosphere,
    loop_subdivision,
    sphere_surface,
)

__all__ = [
    "ScanGeometry",
    "Mesh",
    "Polygon",
    "MeshProjector",
    "Traversal",
    "SubdivisionSurface",
    "loop_subdivision",
    "curve_subdivision",
    "icosphere",
    "sphere_surface",
    "circle_surface",
]
