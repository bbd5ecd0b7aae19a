"""Voxel grids: world <-> index conversion for images and volumes.

A grid is ``(shape, extent)``, the convention of :mod:`bubsub.core.projection.masks`:

* 2D: ``img[row, col]``, ``shape = (rows, cols)``, ``extent = (xmin, xmax,
  ymin, ymax)``; pixel centre ``x = xmin + (col + 0.5) * dx``,
  ``y = ymax - (row + 0.5) * dy`` (row 0 at y max), with
  ``dx = (xmax - xmin) / cols`` and ``dy = (ymax - ymin) / rows``. This is
  ASTRA's 2D ``create_vol_geom(rows, cols, xmin, xmax, ymin, ymax)``.
* 3D: ``vol[z, y, x]``, ``shape = (slices, rows, cols)``, ``extent = (xmin,
  xmax, ymin, ymax, zmin, zmax)``; x and y within a slice as in 2D and
  ``z = zmin + (slice + 0.5) * dz``.

World points are ``[x, y]`` / ``[x, y, z]`` (mm); index coordinates are in
array-axis order ``[row, col]`` / ``[slice, row, col]`` and may be
fractional (pixel centres are at integers). :func:`world_to_index` and
:func:`index_to_world` are the one pair of conversions used by the voxel
reconstruction and segmentation code.

:class:`VoxelGrid` is the grid as one object (as tomosipo's volume
geometry): the validated ``(shape, extent)`` pair, built from an extent or
from a voxel size and centre (:meth:`VoxelGrid.of`, :func:`resolve_grid`),
with its voxel size, centre and conversions. It is a named tuple, so
``shape, extent = grid`` works wherever the pair is expected, and every
voxel driver (:class:`~bubsub.core.voxel.projector3d.VoxelProjector`,
:class:`~bubsub.core.voxel.astra2d.AstraProjector2D`, ``reconstruct_3d``,
``reconstruct_2d``) takes one in place of ``shape``.
"""

from __future__ import annotations

import numbers
from typing import NamedTuple

import numpy as np

from bubsub.core.projection.masks import check_grid

__all__ = ["VoxelGrid", "grid_extent", "resolve_grid", "voxel_sizes", "world_to_index", "index_to_world"]


class VoxelGrid(NamedTuple):
    """A validated voxel grid: ``shape`` (array-axis order) and ``extent`` (mm), see the module docstring.

    Build it with :meth:`of` (which checks it); the fields are then a tuple of ints and a tuple of
    floats. Being a tuple, it unpacks as ``shape, extent = grid``.
    """

    shape: tuple
    extent: tuple

    @classmethod
    def of(cls, shape, extent=None, pixel_size=None, centre=None):
        """The grid of :func:`resolve_grid` (an extent, or a voxel size and centre)."""
        return resolve_grid(shape, extent, pixel_size, centre)

    @property
    def ndim(self):
        """2 or 3."""
        return len(self.shape)

    @property
    def voxel_sizes(self):
        """``(ndim,)`` float: side lengths in array-axis order (``[dy, dx]`` or ``[dz, dy, dx]``), mm."""
        return voxel_sizes(self.shape, self.extent)

    @property
    def centre(self):
        """``(ndim,)`` float: the world position ``[x, y(, z)]`` of the grid's centre, mm."""
        e = np.asarray(self.extent, dtype=float)
        return 0.5 * (e[0::2] + e[1::2])

    def world_to_index(self, points):
        """:func:`world_to_index` on this grid."""
        return world_to_index(points, self.shape, self.extent)

    def index_to_world(self, indices):
        """:func:`index_to_world` on this grid."""
        return index_to_world(indices, self.shape, self.extent)


def grid_extent(shape, pixel_size, centre=None):
    """Extent of a grid of square (cubic) pixels of a given size.

    Parameters
    ----------
    shape : (rows, cols) or (slices, rows, cols) ints
    pixel_size : float
        Pixel (voxel) side length, mm.
    centre : (2,) or (3,) float, optional
        World position ``[x, y(, z)]`` of the grid centre; the origin by default.

    Returns
    -------
    tuple of float
        ``(xmin, xmax, ymin, ymax[, zmin, zmax])``.
    """
    try:
        shp = tuple(int(s) for s in shape)
    except (TypeError, ValueError):
        raise ValueError(f"grid shape must be a tuple of ints, got {shape!r}") from None
    if len(shp) not in (2, 3) or any(s < 1 for s in shp):
        raise ValueError(f"grid shape must be 2 or 3 positive ints, got {shape!r}")
    if isinstance(pixel_size, bool) or not isinstance(pixel_size, numbers.Real):
        raise ValueError(f"pixel_size must be a positive number, got {pixel_size!r}")
    h = float(pixel_size)
    if not (np.isfinite(h) and h > 0):
        raise ValueError(f"pixel_size must be a positive number, got {pixel_size!r}")
    d = len(shp)
    c = np.zeros(d) if centre is None else np.asarray(centre, dtype=float)
    if c.shape != (d,) or not np.all(np.isfinite(c)):
        raise ValueError(f"centre must be {d} finite numbers [x, y{', z' if d == 3 else ''}], got {centre!r}")
    counts = shp[::-1]  # (nx, ny[, nz]) in world-axis order
    ext = []
    for k in range(d):
        half = 0.5 * counts[k] * h
        ext += [float(c[k] - half), float(c[k] + half)]
    return tuple(ext)


def resolve_grid(shape, extent=None, pixel_size=None, centre=None):
    """Validate a grid given either by its extent or by pixel size and centre.

    Parameters
    ----------
    shape : (rows, cols) or (slices, rows, cols) ints, or VoxelGrid
        A VoxelGrid is the whole grid (then no ``extent``, ``pixel_size`` or ``centre``).
    extent : (2 * len(shape),) floats, optional
        ``(xmin, xmax, ymin, ymax[, zmin, zmax])``, mm.
    pixel_size : float, optional
        Square pixel side, mm; used with ``centre`` when ``extent`` is not given.
    centre : (len(shape),) floats, optional
        Grid centre ``[x, y(, z)]``, mm (default the origin); only with ``pixel_size``.

    Returns
    -------
    VoxelGrid
        ``(shape, extent)``: a tuple of int and a tuple of float.

    Raises
    ------
    ValueError
        If both or neither of ``extent`` and ``pixel_size`` are given, or the
        grid is invalid.
    """
    if isinstance(shape, VoxelGrid):
        if extent is not None or pixel_size is not None or centre is not None:
            raise ValueError("a VoxelGrid is the whole grid: give no extent, pixel_size or centre with it")
        shape, extent = shape
    if extent is not None and (pixel_size is not None or centre is not None):
        raise ValueError("give either extent or pixel_size (and centre), not both")
    if extent is None:
        if pixel_size is None:
            raise ValueError("the grid needs an extent or a pixel_size")
        extent = grid_extent(shape, pixel_size, centre)
    return VoxelGrid(*check_grid(shape, extent))


def voxel_sizes(shape, extent):
    """Pixel (voxel) side lengths in array-axis order.

    Returns
    -------
    (ndim,) float
        ``[dy, dx]`` (2D) or ``[dz, dy, dx]`` (3D), mm.
    """
    shp, ext = check_grid(shape, extent)
    d = len(shp)
    sizes = [(ext[2 * k + 1] - ext[2 * k]) / shp[d - 1 - k] for k in range(d)]  # dx, dy(, dz)
    return np.array(sizes[::-1])


def _points(a, d, what):
    p = np.asarray(a, dtype=float)
    if p.ndim == 0 or p.shape[-1] != d:
        raise ValueError(f"{what} must have shape (..., {d}), got {np.shape(a)}")
    return p


def world_to_index(points, shape, extent):
    """Fractional array indices of world points.

    Parameters
    ----------
    points : (..., ndim) float
        World coordinates ``[x, y]`` or ``[x, y, z]``, mm.
    shape, extent
        The grid (see module docstring).

    Returns
    -------
    (..., ndim) float
        ``[row, col]`` or ``[slice, row, col]``; pixel centres are integers.
    """
    shp, ext = check_grid(shape, extent)
    d = len(shp)
    p = _points(points, d, "points")
    h = voxel_sizes(shp, ext)  # array-axis order
    out = np.empty(p.shape, dtype=float)
    # array axes: -1 = x (col), -2 = y (row, decreasing), 0 = z (slice) in 3D
    out[..., d - 1] = (p[..., 0] - ext[0]) / h[d - 1] - 0.5
    out[..., d - 2] = (ext[3] - p[..., 1]) / h[d - 2] - 0.5
    if d == 3:
        out[..., 0] = (p[..., 2] - ext[4]) / h[0] - 0.5
    return out


def index_to_world(indices, shape, extent):
    """World coordinates of (fractional) array indices; inverse of :func:`world_to_index`.

    Parameters
    ----------
    indices : (..., ndim) float
        ``[row, col]`` or ``[slice, row, col]``.
    shape, extent
        The grid.

    Returns
    -------
    (..., ndim) float
        ``[x, y]`` or ``[x, y, z]``, mm.
    """
    shp, ext = check_grid(shape, extent)
    d = len(shp)
    i = _points(indices, d, "indices")
    h = voxel_sizes(shp, ext)
    out = np.empty(i.shape, dtype=float)
    out[..., 0] = ext[0] + (i[..., d - 1] + 0.5) * h[d - 1]
    out[..., 1] = ext[3] - (i[..., d - 2] + 0.5) * h[d - 2]
    if d == 3:
        out[..., 2] = ext[4] + (i[..., 0] + 0.5) * h[0]
    return out
