"""Region averages: liquid fraction and texture tensor on a Cartesian grid and in cylindrical shells.

The analysed domain is the field of view (a cylinder about the rotation
axis, the z axis of the scan geometry, ``|z| <= half_height``) or, where it
is not known, the bubbles' bounding box. It is divided into

* Cartesian cells: ``(nx, ny, nz)`` equal boxes over the domain's bounding box,
  each cell measured where it overlaps the domain;
* cylindrical shells: ``n`` shells of equal width from the axis to the
  domain's radius, over the domain's whole height.

Liquid fraction (FoamQuant's ``LiqFrac_CartesMesh`` on a voxel image): the
fraction of a region not inside any bubble, measured on a regular grid of
sample points (spacing ``spacing``) classified exactly against the meshes
(:func:`bubsub.core.voxel.raster.bubble_mask`, slab by slab, so memory stays
bounded).

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

__all__ = ["Domain", "gas_counts", "region_tables", "GRID_COLUMN_INFO", "SHELL_COLUMN_INFO", "texture_summary"]

#: Most sample points classified at once (one slab of the sample grid).
SLAB_SAMPLES = 4_000_000


@dataclass(frozen=True)
class Domain:
    """The analysed region: a cylinder about the z axis, or a box.

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


def gas_counts(meshes, domain, spacing, grid, shells):
    """Sample points of the domain and those inside bubbles, per Cartesian cell and per shell.

    Parameters
    ----------
    meshes : sequence of Mesh
    domain : Domain
    spacing : float
        Sample spacing, mm.
    grid : (3,) int
        Cells along x, y, z.
    shells : int

    Returns
    -------
    cells : (nx * ny * nz, 2) int
        ``(samples in the domain, of them inside a bubble)``, cells in ``(i, j, k)`` order (``k`` fastest).
    rings : (shells, 2) int
        The same per shell.
    sample_volume : float
        Volume of one sample's cell, mm^3 (the spacing rounded to divide the domain's box).
    """
    from bubsub.core.voxel.raster import bubble_mask, pixel_centres

    lo, hi = np.asarray(domain.lo, dtype=float), np.asarray(domain.hi, dtype=float)
    counts = np.maximum(1, np.ceil((hi - lo) / spacing).astype(int))
    nx, ny, nz = (int(c) for c in counts)
    step = (hi - lo) / counts
    cells = np.zeros((int(np.prod(grid)), 2), dtype=np.int64)
    rings = np.zeros((shells, 2), dtype=np.int64)
    zlo = np.array([np.asarray(m.vertices)[:, 2].min() for m in meshes])
    zhi = np.array([np.asarray(m.vertices)[:, 2].max() for m in meshes])
    per_slab = max(1, SLAB_SAMPLES // (nx * ny))
    for k0 in range(0, nz, per_slab):
        k1 = min(nz, k0 + per_slab)
        z0, z1 = lo[2] + k0 * step[2], lo[2] + k1 * step[2]
        shape, extent = (k1 - k0, ny, nx), (lo[0], hi[0], lo[1], hi[1], z0, z1)
        items = [m for m, a, b in zip(meshes, zlo, zhi) if b >= z0 and a <= z1]
        gas = bubble_mask(items, shape, extent) if items else np.zeros(shape, bool)
        z, y, x = pixel_centres(shape, extent)
        pts = np.stack(np.meshgrid(x, y, z, indexing="ij"), axis=-1)  # (x, y, z, 3)
        pts = pts.transpose(2, 1, 0, 3).reshape(-1, 3)  # the mask's (z, y, x) order
        inside = domain.contains(pts)
        pts, g = pts[inside], gas.ravel()[inside]
        c = _cell_index(pts, domain, grid)
        cells[:, 0] += np.bincount(c, minlength=len(cells))
        cells[:, 1] += np.bincount(c, weights=g, minlength=len(cells)).astype(np.int64)
        s = _shell_index(pts, domain, shells)
        rings[:, 0] += np.bincount(s, minlength=shells)
        rings[:, 1] += np.bincount(s, weights=g, minlength=shells).astype(np.int64)
    return cells, rings, float(np.prod(step))


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
        from bubsub.core.analysis.shape import strain_from_axes

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


def region_tables(meshes, centroids, coordination, truncated, contacts, branches, domain, *, spacing, grid, shells):
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
    spacing : float
        Sample spacing of the liquid fraction, mm.
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
    cells, rings, dv = gas_counts(meshes, domain, spacing, grid, shells)
    centroids = np.asarray(centroids, dtype=float).reshape(-1, 3)
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
                total, gas = cells[c]
                row = {"cell_x": i, "cell_y": j, "cell_z": k}
                for a, idx in zip("xyz", (i, j, k)):
                    ax = "xyz".index(a)
                    row[f"{a}_lo_mm"] = float(lo[ax] + idx * size[ax])
                    row[f"{a}_hi_mm"] = float(lo[ax] + (idx + 1) * size[ax])
                row["region_volume_mm3"] = float(total * dv)
                row["gas_volume_mm3"] = float(gas * dv)
                row["liquid_fraction"] = float(1.0 - gas / total) if total else float("nan")
                _region_stats(row, cell_b == c, coordination, truncated, cell_c == c)
                _texture_columns(row, branches[cell_c == c], "xyz")
                grid_rows.append(row)
    r_out = domain.outer_radius
    shell_b = np.where(in_b, _shell_index(centroids, domain, shells), -1)
    shell_c = np.where(in_c, _shell_index(points, domain, shells), -1)
    local = _cylindrical(points, branches) if len(points) else branches
    shell_rows = []
    for s in range(shells):
        total, gas = rings[s]
        row = {"shell": s, "r_lo_mm": r_out * s / shells, "r_hi_mm": r_out * (s + 1) / shells,
               "z_lo_mm": float(lo[2]), "z_hi_mm": float(hi[2]),
               "region_volume_mm3": float(total * dv), "gas_volume_mm3": float(gas * dv),
               "liquid_fraction": float(1.0 - gas / total) if total else float("nan")}
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
    "region_volume_mm3": ("mm^3", "volume of the region inside the analysed domain (sample points x spacing^3)"),
    "gas_volume_mm3": ("mm^3", "volume of the region inside bubbles (sample points x spacing^3)"),
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
