"""bubsub.core: scan geometries, meshes, subdivision and the Embree mesh projector.

Units are millimetres and 1/mm; projections are float32 arrays with axes
``(angle, row, col)`` (3D) or ``(angle, col)`` (2D).
"""

from .projection.geometry import ScanGeometry
from .projection.mesh import Mesh, Polygon
from .projection.projector import MeshProjector, Traversal
from .projection.subdivision import (
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

# Data side: phantoms, simulation, scan files, mesh files, metrics.
from .io.atomic import atomic_open, atomic_path, atomic_write_bytes, atomic_write_text
from .io.meshio import read_ply, read_polygons_json, write_ply, write_polygons_json
from .io.tables import bubble_table, write_csv
from .metrics import dice_dissimilarity, projection_mse, shapes_dice_dissimilarity
from .foam.containers import liquid_box, liquid_square, sphere_mesh
from .foam.phantoms import BENCHMARK_SEED, FoamPhantom, foam2d, foam3d, foam3d_benchmark
from .voxel.raster import bubble_mask, check_grid, coverage, label_image, pixel_centres, rasterize
from .io.scanfile import Scan, read_scan, theta_from_geometry, write_scan
from .foam.simulate import add_poisson_noise, default_geometry_2d, default_geometry_3d, project_image, simulate_2d, simulate_3d

__all__ += [
    "atomic_open", "atomic_path", "atomic_write_bytes", "atomic_write_text",
    "bubble_table", "read_ply", "read_polygons_json", "write_csv", "write_ply", "write_polygons_json",
    "dice_dissimilarity", "projection_mse", "shapes_dice_dissimilarity",
    "BENCHMARK_SEED", "FoamPhantom", "foam2d", "foam3d", "foam3d_benchmark", "liquid_box", "liquid_square", "sphere_mesh",
    "bubble_mask", "check_grid", "coverage", "label_image", "pixel_centres", "rasterize",
    "Scan", "read_scan", "theta_from_geometry", "write_scan",
    "add_poisson_noise", "default_geometry_2d", "default_geometry_3d", "project_image", "simulate_2d", "simulate_3d",
]

# Voxel side: grids, solvers, ASTRA 2D and numpy 3D reconstructions, segmentation.
from .voxel.grid import grid_extent, index_to_world, resolve_grid, voxel_sizes, world_to_index
from .voxel.segment import binarise, bubble_centres, otsu_threshold
from .voxel.solvers import cgls, lsqr, sirt, tv_pdhg
from .voxel.astra2d import AstraProjector2D, fbp_2d, reconstruct_2d
from .voxel.fdk import fdk, ramp_filter
from .voxel.projector3d import VoxelProjector
from .voxel.reconstruct3d import reconstruct_3d

__all__ += [
    "grid_extent", "index_to_world", "resolve_grid", "voxel_sizes", "world_to_index",
    "binarise", "bubble_centres", "otsu_threshold",
    "cgls", "lsqr", "sirt", "tv_pdhg",
    "AstraProjector2D", "fbp_2d", "reconstruct_2d",
    "VoxelProjector", "fdk", "ramp_filter", "reconstruct_3d",
]
