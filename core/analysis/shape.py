"""Shape of one bubble from its closed triangle mesh: size, sphericity, shape tensor, internal strain.

Every integral is exact for the polyhedron the mesh encloses (divergence
theorem, one signed tetrahedron per face and a reference point), so the only
error is the mesh's own distance from the true surface.

Definitions (FoamQuant's, on a mesh instead of voxels)
-------------------------------------------------------
* volume ``V``, surface area ``A``, centroid ``c``;
* equivalent radius ``r = (3 V / (4 pi))^(1/3)``;
* sphericity ``pi^(1/3) (6 V)^(2/3) / A`` (1 for a ball, less for any other shape);
* shape tensor ``M = (1/V) integral (x - c)(x - c)^T dV`` (mm^2), the second central
  moment of the solid. An ellipsoid of semi-axes ``a >= b >= c`` has eigenvalues
  ``a^2/5, b^2/5, c^2/5`` along its axes, so ``semi_axis_i = sqrt(5 lambda_i)`` are the
  semi-axes of the ellipsoid with the same moments (FoamQuant's ``RegionProp`` fits the
  same ellipsoid to a label's inertia tensor);
* internal strain ``U_i = ln(semi_axis_i / (semi_axis_1 semi_axis_2 semi_axis_3)^(1/3))``
  (FoamQuant ``InternalStrain``, ``dim=1``), its von Mises invariant
  ``U = sqrt(((U_1 - U_2)^2 + (U_1 - U_3)^2 + (U_2 - U_3)^2) / 2)``, and the type
  ``+1`` (oblate: the shortest axis departs most from the mean) or ``-1`` (prolate).
"""

from __future__ import annotations

import numpy as np

__all__ = ["solid_moments", "bubble_shape", "strain_from_axes", "SHAPE_COLUMN_INFO", "SHAPE_COLUMNS"]


def solid_moments(vertices, faces):
    """Volume, centroid and second central moment of the solid a closed, outward mesh encloses.

    Parameters
    ----------
    vertices : (n, 3) float
        mm.
    faces : (m, 3) int
        Outward oriented (counter-clockwise seen from outside).

    Returns
    -------
    volume : float
        mm^3.
    centroid : (3,) float
        mm.
    moment : (3, 3) float
        ``integral (x - c)(x - c)^T dV``, mm^5 (divide by the volume for the shape tensor).
    """
    v = np.asarray(vertices, dtype=float)
    origin = v.mean(axis=0)  # tetrahedra from a point near the solid: no cancellation of large terms
    p = v - origin
    f = np.asarray(faces)
    a, b, c = p[f[:, 0]], p[f[:, 1]], p[f[:, 2]]
    det = np.einsum("ij,ij->i", a, np.cross(b, c))  # 6 x signed volume of (origin, a, b, c)
    volume = det.sum() / 6.0
    s = a + b + c
    first = (det[:, None] * s).sum(axis=0) / 24.0  # integral of x: volume_t x (a + b + c) / 4 per tetrahedron
    # integral of x x^T over a tetrahedron with a vertex at 0: volume_t / 20 (a a^T + b b^T + c c^T + s s^T)
    second = np.einsum("i,ij,ik->jk", det, a, a) + np.einsum("i,ij,ik->jk", det, b, b) \
        + np.einsum("i,ij,ik->jk", det, c, c) + np.einsum("i,ij,ik->jk", det, s, s)
    second /= 120.0
    centre = first / volume
    moment = second - volume * np.outer(centre, centre)
    return float(volume), centre + origin, 0.5 * (moment + moment.T)


def strain_from_axes(semi_axes):
    """FoamQuant's internal strain of an ellipsoid's semi-axes.

    Parameters
    ----------
    semi_axes : (..., 3) float
        Positive, mm (or any length unit).

    Returns
    -------
    strain : (..., 3) float
        ``ln(a_i / (a_1 a_2 a_3)^(1/3))``, summing to 0.
    von_mises : (...,) float
    kind : (...,) int
        +1 oblate, -1 prolate (FoamQuant's ``type``).
    """
    a = np.asarray(semi_axes, dtype=float)
    log = np.log(a)
    u = log - log.mean(axis=-1, keepdims=True)
    d = u[..., [0, 0, 1]] - u[..., [1, 2, 2]]
    vm = np.sqrt(0.5 * (d ** 2).sum(axis=-1))
    kind = np.where(np.abs(u.min(axis=-1)) > np.abs(u.max(axis=-1)), 1, -1)
    return u, vm, kind


def _axis_sign(vectors):
    """Columns of ``vectors`` flipped so that each one's largest component is positive (a fixed sign)."""
    big = np.argmax(np.abs(vectors), axis=0)
    sign = np.sign(vectors[big, np.arange(vectors.shape[1])])
    return vectors * np.where(sign == 0, 1.0, sign)


def bubble_shape(mesh):
    """The shape quantities of one bubble (see the module docstring).

    Parameters
    ----------
    mesh : Mesh
        Closed, outward (the refined bubble surface).

    Returns
    -------
    dict
        Keys of :data:`SHAPE_COLUMNS`; ``axis_i_x|y|z`` are the unit eigenvectors of the
        shape tensor, ``i = 1`` the longest.
    """
    faces = np.asarray(mesh.faces)
    volume, centroid, moment = solid_moments(mesh.vertices, faces)
    if not volume > 0:
        raise ValueError(f"a bubble mesh encloses a non-positive volume ({volume:.3g} mm^3)")
    tri = mesh.vertices[faces]
    area = float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())
    lam, vec = np.linalg.eigh(moment / volume)
    lam, vec = lam[::-1], _axis_sign(vec[:, ::-1])
    semi = np.sqrt(5.0 * np.maximum(lam, 0.0))
    row = {
        "centroid_x_mm": centroid[0], "centroid_y_mm": centroid[1], "centroid_z_mm": centroid[2],
        "volume_mm3": volume, "surface_area_mm2": area,
        "equivalent_radius_mm": np.cbrt(3.0 * volume / (4.0 * np.pi)),
        "sphericity": np.pi ** (1 / 3) * (6.0 * volume) ** (2 / 3) / area,
    }
    for i in range(3):
        row[f"shape_eigenvalue_{i + 1}_mm2"] = lam[i]
    for i in range(3):
        row[f"semi_axis_{i + 1}_mm"] = semi[i]
    for i in range(3):
        for k, name in enumerate("xyz"):
            row[f"axis_{i + 1}_{name}"] = vec[k, i]
    if np.all(semi > 0):
        u, vm, kind = strain_from_axes(semi)
    else:  # a flat (degenerate) bubble has no finite strain
        u, vm, kind = np.full(3, np.nan), np.nan, 0
    for i in range(3):
        row[f"strain_{i + 1}"] = u[i]
    row["strain_von_mises"] = vm
    row["shape_type"] = int(kind)
    return {k: (float(v) if k != "shape_type" else v) for k, v in row.items()}


#: ``column: (unit, meaning)`` of the shape columns of ``bubbles.csv``.
SHAPE_COLUMN_INFO = {
    **{f"centroid_{a}_mm": ("mm", f"{a} coordinate of the centroid of the solid the refined surface encloses")
       for a in "xyz"},
    "volume_mm3": ("mm^3", "volume enclosed by the refined surface"),
    "surface_area_mm2": ("mm^2", "area of the refined surface"),
    "equivalent_radius_mm": ("mm", "radius of the ball of the same volume, (3 V / 4 pi)^(1/3)"),
    "sphericity": ("1", "pi^(1/3) (6 V)^(2/3) / A: 1 for a ball, less for any other shape"),
    **{f"shape_eigenvalue_{i}_mm2": ("mm^2", f"eigenvalue {i} (descending) of the shape tensor "
                                             f"(1/V) integral (x - c)(x - c)^T dV") for i in (1, 2, 3)},
    **{f"semi_axis_{i}_mm": ("mm", f"semi-axis {i} of the ellipsoid with the same shape tensor, "
                                   f"sqrt(5 x eigenvalue {i})") for i in (1, 2, 3)},
    **{f"axis_{i}_{a}": ("1", f"{a} component of the unit eigenvector of shape-tensor eigenvalue {i} "
                              f"(sign: its largest component positive)") for i in (1, 2, 3) for a in "xyz"},
    **{f"strain_{i}": ("1", f"internal strain along axis {i}: ln(semi_axis_{i} / (semi_axis_1 semi_axis_2 "
                            f"semi_axis_3)^(1/3)) (FoamQuant)") for i in (1, 2, 3)},
    "strain_von_mises": ("1", "von Mises invariant of the internal strain, sqrt(sum_(i<j) (U_i - U_j)^2 / 2)"),
    "shape_type": ("1", "+1 oblate (the shortest axis departs most from the mean), -1 prolate (FoamQuant's type)"),
}

#: Keys of :func:`bubble_shape`, in the order of ``bubbles.csv``.
SHAPE_COLUMNS = tuple(SHAPE_COLUMN_INFO)
