"""bubsub.core: scan geometries, meshes, subdivision and the Embree mesh projector.

Units are millimetres and 1/mm; projections are float32 arrays with axes
``(angle, row, col)`` (3D) or ``(angle, col)`` (2D).
"""

from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.projection.mesh import Mesh, Polygon
from bubsub.core.projection.projector import MeshProjector, Traversal
from bubsub.core.projection.subdivision import (
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
from bubsub.core.io.atomic import atomic_open, atomic_path, atomic_write_bytes, atomic_write_text
from bubsub.core.io.meshio import read_ply, read_polygons_json, write_ply, write_polygons_json
from bubsub.core.io.tables import write_csv
from bubsub.core.metrics import dice_dissimilarity, projection_mse, shapes_dice_dissimilarity
from bubsub.core.foam.containers import liquid_box, liquid_square, sphere_mesh
from bubsub.core.foam.phantoms import BENCHMARK_SEED, FoamPhantom, foam2d, foam3d, foam3d_benchmark
from bubsub.core.projection.masks import bubble_mask, check_grid, coverage, label_image, pixel_centres, rasterize
from bubsub.core.io.scanfile import Scan, read_scan, theta_from_geometry, write_scan
from bubsub.core.foam.simulate import (add_poisson_noise, default_geometry_2d, default_geometry_3d, project_image,
                                       simulate_2d, simulate_3d)

__all__ += [
    "atomic_open", "atomic_path", "atomic_write_bytes", "atomic_write_text",
    "read_ply", "read_polygons_json", "write_csv", "write_ply", "write_polygons_json",
    "dice_dissimilarity", "projection_mse", "shapes_dice_dissimilarity",
    "BENCHMARK_SEED", "FoamPhantom", "foam2d", "foam3d", "foam3d_benchmark", "liquid_box", "liquid_square", "sphere_mesh",
    "bubble_mask", "check_grid", "coverage", "label_image", "pixel_centres", "rasterize",
    "Scan", "read_scan", "theta_from_geometry", "write_scan",
    "add_poisson_noise", "default_geometry_2d", "default_geometry_3d", "project_image", "simulate_2d", "simulate_3d",
]

# Voxel side: grids, solvers, ASTRA 2D and numpy 3D reconstructions, segmentation.
from bubsub.core.voxel.grid import grid_extent, index_to_world, resolve_grid, voxel_sizes, world_to_index
from bubsub.core.voxel.segment import binarise, bubble_centres, otsu_threshold
from bubsub.core.voxel.solvers import cgls, lsqr, sirt, tv_pdhg
from bubsub.core.voxel.astra2d import AstraProjector2D, fbp_2d, reconstruct_2d
from bubsub.core.voxel.fdk import fdk, ramp_filter
from bubsub.core.voxel.projector3d import VoxelProjector
from bubsub.core.voxel.reconstruct3d import reconstruct_3d

__all__ += [
    "grid_extent", "index_to_world", "resolve_grid", "voxel_sizes", "world_to_index",
    "binarise", "bubble_centres", "otsu_threshold",
    "cgls", "lsqr", "sirt", "tv_pdhg",
    "AstraProjector2D", "fbp_2d", "reconstruct_2d",
    "VoxelProjector", "fdk", "ramp_filter", "reconstruct_3d",
]
