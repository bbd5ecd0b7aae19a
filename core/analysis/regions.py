"""Region averages: liquid fraction and texture tensor on a Cartesian grid and in cylindrical shells.

The analysed domain (:class:`Domain`) is a box, a cylinder about the
rotation axis (the z axis of the scan geometry) or the part of a box inside
such a cylinder: the sample (a liquid box, a column) within the field of view
(the cylinder every projection sees, ``|z| <= half_height``), so that the
liquid fraction counts no air around the sample. It is divided into

* Cartesian cells: ``(nx, ny, nz)`` equal boxes over the domain's bounding box,
  each cell measured where it overlaps the domain;
* cylindrical shells: ``n`` shells of equal width from the axis to the
  domain's radius, over the domain's whole height.

Liquid fraction (FoamQuant's ``LiqFrac_CartesMesh`` on a voxel image): the
fraction of a region not inside any bubble. Each bubble's exact volume is
cut into small pieces of known volume and position and shared among the
regions it crosses (:func:`region_volumes`), with no voxels.

Texture tensor (Graner et al. 2008; FoamQuant ``Texture``): the mean of
``l l^T`` over the contacts whose contact point lies in the region, ``l`` the
branch vector joining the two bubbles' centroids (mm^2). In shells it is
written in the local cylindrical frame ``(r, phi, z)`` of each contact
point. Its eigenvalues give the texture strain ``U_i = ln(lambda_i /
(lambda_1 lambda_2 lambda_3)^(1/3)) / 2`` (FoamQuant, ``dim=2``) and its von
Mises invariant.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bubsub.core.analysis.shape import strain_from_axes

__all__ = ["Domain", "region_volumes", "region_tables", "GRID_COLUMN_INFO", "SHELL_COLUMN_INFO", "texture_summary"]

#: Radial slices of each (centre, face) tetrahedron when a bubble's volume is shared among regions.
RADIAL_LAYERS = 8
#: In-plane points per axis of the grid that measures the regions' areas.
AREA_SAMPLES = 1000


@dataclass(frozen=True)
class Domain:
    """The analysed region: the points of the box ``lo``-``hi`` within ``radius`` of the z axis.

    A box (``radius`` None), a cylinder about the z axis (the box is the
    cylinder's bounding box) or a box cut by such a cylinder: the intersection
    of any two of them is one of the three (:meth:`intersect`).

    Attributes
    ----------
    lo, hi : (3,) float
        Bounding box, mm.
    radius : float or None
        Cylinder radius about the z axis (mm); None for the box itself.
    """

    lo: tuple
    hi: tuple
    radius: float | None = None

    @classmethod
    def field_of_view(cls, radius, half_height):
        """The field of view of a circular scan: ``x^2 + y^2 <= radius^2``, ``|z| <= half_height``."""
        if not (radius > 0 and half_height > 0):
            raise ValueError(f"the field of view needs a positive radius and half-height, got {radius}, {half_height}")
        return cls((-radius, -radius, -half_height), (radius, radius, half_height), float(radius))

    @classmethod
    def cylinder(cls, radius, z_lo, z_hi):
        """The cylinder ``x^2 + y^2 <= radius^2``, ``z_lo <= z <= z_hi`` (mm)."""
        r = float(radius)
        if not (r > 0 and np.isfinite(r)):
            raise ValueError(f"a cylinder needs a positive, finite radius, got {radius!r} mm")
        box = cls.box((-r, r, -r, r, z_lo, z_hi))
        return cls(box.lo, box.hi, r)

    @classmethod
    def box(cls, bounds):
        """The box ``(x0, x1, y0, y1, z0, z1)`` (mm), each lower bound below its upper one."""
        b = np.asarray(bounds, dtype=float).reshape(-1)
        if b.shape != (6,) or not np.all(np.isfinite(b)):
            raise ValueError(f"a box needs six finite bounds x0, x1, y0, y1, z0, z1 (mm), got {bounds!r}")
        lo, hi = b[0::2], b[1::2]
        if np.any(hi <= lo):
            raise ValueError(f"a box needs each lower bound below its upper one, got {bounds!r}")
        return cls(tuple(map(float, lo)), tuple(map(float, hi)), None)

    def intersect(self, other):
        """The points of both domains (a box, a cylinder about the z axis, or a box cut by a cylinder).

        Raises
        ------
        ValueError
            If the two do not overlap.
        """
        lo, hi = np.maximum(self.lo, other.lo), np.minimum(self.hi, other.hi)
        radii = [r for r in (self.radius, other.radius) if r is not None]
        r = min(radii) if radii else None
        if r is not None:
            lo[:2], hi[:2] = np.maximum(lo[:2], -r), np.minimum(hi[:2], r)
        if np.any(hi <= lo):
            raise ValueError(f"the domains {self.describe()} and {other.describe()} do not overlap")
        if r is not None:
            corners = np.hypot(np.maximum(np.abs(lo[0]), np.abs(hi[0])), np.maximum(np.abs(lo[1]), np.abs(hi[1])))
            near = np.hypot(0.0 if lo[0] <= 0 <= hi[0] else min(abs(lo[0]), abs(hi[0])),
                            0.0 if lo[1] <= 0 <= hi[1] else min(abs(lo[1]), abs(hi[1])))
            if near >= r:
                raise ValueError(f"the domains {self.describe()} and {other.describe()} do not overlap")
            if corners <= r:  # the cylinder does not cut the box
                r = None
        return Domain(tuple(map(float, lo)), tuple(map(float, hi)), None if r is None else float(r))

    @property
    def kind(self):
        """``"box"``, ``"cylinder"`` (its bounding box is ``lo``-``hi``) or ``"box within cylinder"``."""
        if self.radius is None:
            return "box"
        r = self.radius
        square = np.allclose([self.lo[0], self.lo[1], self.hi[0], self.hi[1]], [-r, -r, r, r], rtol=1e-12, atol=0)
        return "cylinder" if square else "box within cylinder"

    def describe(self):
        """The domain as JSON: ``{"kind", "lo_mm", "hi_mm", "radius_mm"}`` (radius None for a box)."""
        return {"kind": self.kind, "lo_mm": [float(v) for v in self.lo], "hi_mm": [float(v) for v in self.hi],
                "radius_mm": self.radius}

    @classmethod
    def around(cls, meshes):
        """The bounding box of the meshes' vertices."""
        v = np.concatenate([np.asarray(m.vertices) for m in meshes])
        return cls(tuple(v.min(axis=0)), tuple(v.max(axis=0)), None)

    def contains(self, points):
        """(k,) bool: the points inside the domain."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        ok = np.all((p >= np.asarray(self.lo)) & (p <= np.asarray(self.hi)), axis=1)
        if self.radius is not None:
            ok &= np.hypot(p[:, 0], p[:, 1]) <= self.radius
        return ok

    @property
    def outer_radius(self):
        """Largest distance of the domain from the z axis, mm."""
        if self.radius is not None:
            return self.radius
        corners = np.array([[x, y] for x in (self.lo[0], self.hi[0]) for y in (self.lo[1], self.hi[1])])
        return float(np.hypot(corners[:, 0], corners[:, 1]).max())


def _cell_index(points, domain, grid):
    lo, hi = np.asarray(domain.lo), np.asarray(domain.hi)
    n = np.asarray(grid)
    k = np.floor((points - lo) / (hi - lo) * n).astype(np.int64)
    k = np.clip(k, 0, n - 1)
    return (k[:, 0] * n[1] + k[:, 1]) * n[2] + k[:, 2]


def _shell_index(points, domain, shells):
    r = np.hypot(points[:, 0], points[:, 1])
    return np.clip(np.floor(r / domain.outer_radius * shells).astype(np.int64), 0, shells - 1)


def _plane(domain, grid, shells, x, y):
    """Points of an in-plane grid (at the domain's bottom): inside the domain, Cartesian (x, y) cell, shell."""
    X, Y = np.meshgrid(x, y)
    pts = np.stack([X.ravel(), Y.ravel(), np.full(X.size, float(domain.lo[2]))], axis=1)
    return domain.contains(pts), _cell_index(pts, domain, grid) // int(grid[2]), _shell_index(pts, domain, shells)


def region_volumes(meshes, centroids, domain, grid, shells):
    """Volume of each region and the bubbles' gas volume in it.

    The gas: every face and the bubble's centroid span a signed tetrahedron;
    the tetrahedra sum to the enclosed volume exactly, whatever the bubble's
    shape. Each is cut into :data:`RADIAL_LAYERS` slices parallel to its face,
    whose volumes and centroids are exact, and a slice's volume goes to the
    region (and the domain) holding its centroid
    (:func:`bubsub.core.analysis.kernels.share_volumes`); the slices are a
    fraction of the radius deep and a face across, so only the slices a
    region's border cuts are misplaced, by less than their size. The regions'
    own volumes come from a fine in-plane grid (:data:`AREA_SAMPLES` points per
    axis over the domain's box) times their exact heights.

    Parameters
    ----------
    meshes : sequence of Mesh
    centroids : (n, 3) float
        mm.
    domain : Domain
    grid : (3,) int
        Cells along x, y, z.
    shells : int

    Returns
    -------
    cell_volume, cell_gas : (nx * ny * nz,) float
        mm^3; cells in ``(i, j, k)`` order (``k`` fastest).
    shell_volume, shell_gas : (shells,) float
        mm^3.
    """
    lo, hi = np.asarray(domain.lo, dtype=float), np.asarray(domain.hi, dtype=float)
    size = hi - lo
    gz, n_cells = int(grid[2]), int(np.prod(grid))
    n = AREA_SAMPLES
    x = lo[0] + (np.arange(n) + 0.5) * size[0] / n
    y = lo[1] + (np.arange(n) + 0.5) * size[1] / n
    inside, cell_xy, ring = _plane(domain, grid, shells, x, y)
    da = size[0] * size[1] / n ** 2
    cell_volume = np.repeat(np.bincount(cell_xy[inside], minlength=n_cells // gz) * da, gz) * (size[2] / gz)
    shell_volume = np.bincount(ring[inside], minlength=shells) * da * size[2]
    from bubsub.core.analysis.kernels import pack, share_volumes

    cell_gas, shell_gas = np.zeros(n_cells), np.zeros(shells)
    meshes = list(meshes)
    if meshes:
        vertices, faces, v0, f0 = pack([m.vertices for m in meshes], [m.faces for m in meshes])
        share_volumes(vertices, faces, v0, f0, np.ascontiguousarray(centroids, dtype=float), RADIAL_LAYERS, lo, hi,
                      -1.0 if domain.radius is None else float(domain.radius), np.asarray(grid, dtype=np.int64),
                      int(shells), float(domain.outer_radius), cell_gas, shell_gas)
    return cell_volume, cell_gas, shell_volume, shell_gas


def _cylindrical(points, vectors):
    """Vectors in the local ``(r, phi, z)`` frame at the points (on the axis: the x, y frame)."""
    phi = np.arctan2(points[:, 1], points[:, 0])
    c, s = np.cos(phi), np.sin(phi)
    vr = c * vectors[:, 0] + s * vectors[:, 1]
    vp = -s * vectors[:, 0] + c * vectors[:, 1]
    return np.stack([vr, vp, vectors[:, 2]], axis=1)


def texture_summary(branches):
    """Mean texture tensor of branch vectors and its eigenvalues and texture strain.

    Parameters
    ----------
    branches : (k, 3) float
        Branch vectors, mm.

    Returns
    -------
    tensor : (3, 3) float
        ``mean(l l^T)``, mm^2 (NaN without contacts).
    eigenvalues : (3,) float
        Descending, mm^2.
    strain : (3,) float
        ``ln(lambda_i / geometric mean) / 2`` (NaN unless all eigenvalues are positive).
    von_mises : float
    """
    b = np.asarray(branches, dtype=float).reshape(-1, 3)
    if not len(b):
        nan3 = np.full(3, np.nan)
        return np.full((3, 3), np.nan), nan3, nan3, np.nan
    t = b.T @ b / len(b)
    lam = np.linalg.eigvalsh(t)[::-1]
    if np.all(lam > 0):
        u, vm, _ = strain_from_axes(np.sqrt(lam))  # ln(sqrt(lambda_i) / mean) = ln(lambda_i / mean) / 2
    else:
        u, vm = np.full(3, np.nan), np.nan
    return t, lam, u, float(vm)


def _texture_columns(row, branches, names):
    t, lam, u, vm = texture_summary(branches)
    for (a, b) in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)):
        row[f"texture_{names[a]}{names[b]}_mm2"] = float(t[a, b])
    for i in range(3):
        row[f"texture_eigenvalue_{i + 1}_mm2"] = float(lam[i])
    for i in range(3):
        row[f"texture_strain_{i + 1}"] = float(u[i])
    row["texture_strain_von_mises"] = vm


def _region_stats(row, member_b, coordination, truncated, member_c):
    row["bubbles"] = int(member_b.sum())
    whole = member_b & (truncated == 0)
    row["mean_coordination"] = float(coordination[whole].mean()) if whole.any() else float("nan")
    row["contacts"] = int(member_c.sum())


def region_tables(meshes, centroids, coordination, truncated, contacts, branches, domain, *, grid, shells):
    """Rows of the Cartesian-grid and cylindrical-shell tables.

    Parameters
    ----------
    meshes : sequence of Mesh
    centroids : (n, 3) float
        Bubble centroids, mm.
    coordination : (n,) int
    truncated : (n,) int
        1 for bubbles cut by the field of view (left out of the mean coordination).
    contacts : Contacts
    branches : (k, 3) float
        The contacts' branch vectors, mm.
    domain : Domain
    grid : (3,) int
    shells : int

    Returns
    -------
    grid_rows, shell_rows : list of dict
        Columns of :data:`GRID_COLUMN_INFO` and :data:`SHELL_COLUMN_INFO`.
    """
    grid = tuple(int(g) for g in grid)
    if len(grid) != 3 or min(grid) < 1 or int(shells) < 1:
        raise ValueError(f"the grid needs three positive cell counts and at least one shell, got {grid}, {shells}")
    shells = int(shells)
    centroids = np.asarray(centroids, dtype=float).reshape(-1, 3)
    cell_volume, cell_gas, shell_volume, shell_gas = region_volumes(meshes, centroids, domain, grid, shells)
    points = np.asarray(contacts.point, dtype=float).reshape(-1, 3)
    branches = np.asarray(branches, dtype=float).reshape(-1, 3)
    coordination, truncated = np.asarray(coordination), np.asarray(truncated)
    in_b, in_c = domain.contains(centroids), domain.contains(points)
    cell_b = np.where(in_b, _cell_index(centroids, domain, grid), -1)
    cell_c = np.where(in_c, _cell_index(points, domain, grid), -1)
    lo, hi = np.asarray(domain.lo), np.asarray(domain.hi)
    size = (hi - lo) / np.asarray(grid)
    grid_rows = []
    for i in range(grid[0]):
        for j in range(grid[1]):
            for k in range(grid[2]):
                c = (i * grid[1] + j) * grid[2] + k
                total, gas = cell_volume[c], cell_gas[c]
                row = {"cell_x": i, "cell_y": j, "cell_z": k}
                for a, idx in zip("xyz", (i, j, k)):
                    ax = "xyz".index(a)
                    row[f"{a}_lo_mm"] = float(lo[ax] + idx * size[ax])
                    row[f"{a}_hi_mm"] = float(lo[ax] + (idx + 1) * size[ax])
                row["region_volume_mm3"] = float(total)
                row["gas_volume_mm3"] = float(gas)
                row["liquid_fraction"] = float(1.0 - gas / total) if total > 0 else float("nan")
                _region_stats(row, cell_b == c, coordination, truncated, cell_c == c)
                _texture_columns(row, branches[cell_c == c], "xyz")
                grid_rows.append(row)
    r_out = domain.outer_radius
    shell_b = np.where(in_b, _shell_index(centroids, domain, shells), -1)
    shell_c = np.where(in_c, _shell_index(points, domain, shells), -1)
    local = _cylindrical(points, branches) if len(points) else branches
    shell_rows = []
    for s in range(shells):
        total, gas = shell_volume[s], shell_gas[s]
        row = {"shell": s, "r_lo_mm": r_out * s / shells, "r_hi_mm": r_out * (s + 1) / shells,
               "z_lo_mm": float(lo[2]), "z_hi_mm": float(hi[2]),
               "region_volume_mm3": float(total), "gas_volume_mm3": float(gas),
               "liquid_fraction": float(1.0 - gas / total) if total > 0 else float("nan")}
        _region_stats(row, shell_b == s, coordination, truncated, shell_c == s)
        _texture_columns(row, local[shell_c == s], ("r", "phi", "z"))
        shell_rows.append(row)
    return grid_rows, shell_rows


def _texture_info(names, frame):
    info = {}
    for (a, b) in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)):
        info[f"texture_{names[a]}{names[b]}_mm2"] = (
            "mm^2", f"{names[a]}{names[b]} component ({frame}) of the texture tensor, the mean of l l^T over the "
                    f"contacts whose contact point lies in the region (l: branch vector)")
    for i in (1, 2, 3):
        info[f"texture_eigenvalue_{i}_mm2"] = ("mm^2", f"eigenvalue {i} (descending) of the texture tensor")
    for i in (1, 2, 3):
        info[f"texture_strain_{i}"] = ("1", f"texture strain ln(eigenvalue {i} / geometric mean of the "
                                            f"eigenvalues) / 2 (FoamQuant)")
    info["texture_strain_von_mises"] = ("1", "von Mises invariant of the texture strain")
    return info


_COMMON_INFO = {
    "region_volume_mm3": ("mm^3", "volume of the region inside the analysed domain"),
    "gas_volume_mm3": ("mm^3", "volume of bubbles in the region (each bubble's volume cut into small pieces shared "
                               "among the regions holding them)"),
    "liquid_fraction": ("1", "fraction of the region outside every bubble (1 - gas / region)"),
    "bubbles": ("1", "bubbles whose centroid lies in the region"),
    "mean_coordination": ("1", "mean coordination of those bubbles, those cut by the field of view left out"),
    "contacts": ("1", "contacts whose contact point lies in the region"),
}

#: ``column: (unit, meaning)`` of the Cartesian-grid table.
GRID_COLUMN_INFO = {
    **{f"cell_{a}": ("1", f"cell index along {a} (0 at the low end)") for a in "xyz"},
    **{f"{a}_{e}_mm": ("mm", f"{'lower' if e == 'lo' else 'upper'} {a} bound of the cell") for a in "xyz"
       for e in ("lo", "hi")},
    **_COMMON_INFO,
    **_texture_info("xyz", "Cartesian frame"),
}

#: ``column: (unit, meaning)`` of the cylindrical-shell table.
SHELL_COLUMN_INFO = {
    "shell": ("1", "shell index, 0 at the rotation axis"),
    "r_lo_mm": ("mm", "inner radius of the shell (distance from the rotation axis, the z axis)"),
    "r_hi_mm": ("mm", "outer radius of the shell"),
    "z_lo_mm": ("mm", "lower z bound of the shell"),
    "z_hi_mm": ("mm", "upper z bound of the shell"),
    **_COMMON_INFO,
    **_texture_info(("r", "phi", "z"), "local cylindrical frame of each contact point"),
}
