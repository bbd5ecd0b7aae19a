"""Shape of one bubble from its closed triangle mesh: size, sphericity, shape tensor, internal strain.

The volume, centroid and shape tensor are exact integrals over the
polyhedron the mesh encloses (divergence theorem, one signed tetrahedron per
face and a reference point): that polyhedron is what the fit matched to the
projections, so its volume is the data's.

The area is the smooth surface's. A bubble's mesh is a Loop subdivision
surface cut off after a few levels; its flat facets have a faceting error in
area and volume of second order in the edge length, a quarter per further
level, which shows in the sphericity (about -0.001 at bubsub's 642 vertices,
of the size of the differences between real bubbles' sphericities). One more
Loop step of the mesh and Richardson's extrapolation of the two levels
(``X_smooth = X_1 + (X_1 - X_0) / 3``) remove that error, and the area is
that of the smooth surface at the polyhedron's volume,
``A = A_smooth (V / V_smooth)^(2/3)``, so that the sphericity is the smooth
surface's and still ``pi^(1/3) (6 V)^(2/3) / A`` of the table's columns. For a
mesh that is not itself a subdivision surface, the smooth surface is the
Loop limit of that mesh taken as a control mesh.

Definitions (FoamQuant's, on a mesh instead of voxels)
-------------------------------------------------------
* volume ``V``, surface area ``A``, centroid ``c``;
* equivalent diameter ``d = (6 V / pi)^(1/3)``, that of the ball of the same volume;
* sphericity ``pi^(1/3) (6 V)^(2/3) / A`` (1 for a ball, less for any other shape);
* ``sphericity_ellipsoid``: FoamQuant's ``RegionProp`` sphericity, that of the
  ellipsoid of the same shape tensor (volume ``4/3 pi a b c``, Knud Thomsen's
  area ``4 pi ((a^p b^p + a^p c^p + b^p c^p) / 3)^(1/p)``, ``p = 1.6``): the
  number to set beside FoamQuant's, equal to ``sphericity`` for an ellipsoid
  (to Thomsen's approximation, at most about 1 %) and usually above it for a shape
  that departs from its ellipsoid;
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

from bubsub.core.io.columns import BUBBLE_COLUMN_INFO
from bubsub.core.io.tables import BUBBLE_COLUMNS_2D, BUBBLE_COLUMNS_3D
from bubsub.core.projection.items import bubble_ids, resolve_items
from bubsub.core.projection.mesh import Mesh, Polygon, equivalent_radius
from bubsub.core.projection.subdivision import loop_subdivision

__all__ = ["solid_moments", "bubble_shape", "bubble_shapes", "bubble_sizes", "bubble_table", "strain_from_axes",
           "thomsen_area", "SHAPE_COLUMN_INFO", "SHAPE_COLUMNS"]

#: Knud Thomsen's exponent in FoamQuant's ellipsoid area.
THOMSEN_P = 1.6


def _moments(vertex_arrays, face_arrays):
    """Volume, area, centroid and shape tensor of many closed meshes in one pass
    (:func:`bubsub.core.analysis.kernels.moments`, tetrahedra about each mesh's vertex mean).

    Returns
    -------
    volume, area : (n,) float
    centroid : (n, 3) float
    tensor : (n, 3, 3) float
        ``(1/V) integral (x - c)(x - c)^T dV``.
    """
    from bubsub.core.analysis.kernels import moments, pack

    vertices, faces, v0, f0 = pack(vertex_arrays, face_arrays)
    n = len(vertex_arrays)
    origin = np.add.reduceat(vertices, v0[:-1], axis=0) / np.diff(v0)[:, None]
    volume, area, first, second = np.empty(n), np.empty(n), np.empty((n, 3)), np.empty((n, 3, 3))
    moments(vertices, faces, v0, f0, origin, volume, area, first, second)
    with np.errstate(divide="ignore", invalid="ignore"):
        centre = first / volume[:, None]
        tensor = second / volume[:, None, None] - centre[:, :, None] * centre[:, None, :]
    return volume, area, centre + origin, tensor


def _smooth_volume_area(vertex_arrays, face_arrays, volume, area):
    """Volume and area of the meshes' smooth (Loop limit) surfaces, by Richardson's extrapolation.

    Parameters
    ----------
    vertex_arrays, face_arrays : sequences of (n_i, 3) float and (m_i, 3) int
        Closed manifold meshes.
    volume, area : (n,) float
        Of the meshes themselves (:func:`_moments`).

    Returns
    -------
    volume, area : (n,) float
        ``X_1 + (X_1 - X_0) / 3`` with ``X_1`` of the meshes after one more Loop step.
    """
    steps = {}  # bubbles of one reconstruction share a few topologies: one matrix each
    finer_v, finer_f = [], []
    for k, (v, f) in enumerate(zip(vertex_arrays, face_arrays)):
        f = np.asarray(f)
        key = (len(v), f.shape, f.tobytes())
        if key not in steps:
            try:
                steps[key] = loop_subdivision(f, len(v), 1)
            except ValueError as e:
                raise ValueError(f"bubble {k}: {e}") from None
        S, fine = steps[key]
        finer_v.append(S @ np.asarray(v, dtype=float))
        finer_f.append(fine)
    v1, a1, _, _ = _moments(finer_v, finer_f)
    return v1 + (v1 - volume) / 3.0, a1 + (a1 - area) / 3.0


def _checked_moments(meshes):
    vertex_arrays, face_arrays = [m.vertices for m in meshes], [m.faces for m in meshes]
    volume, mesh_area, centroid, moment = _moments(vertex_arrays, face_arrays)
    if np.any(~(volume > 0)):
        k = int(np.argmin(volume))
        raise ValueError(f"bubble {k} encloses a non-positive volume ({volume[k]:.3g} mm^3)")
    smooth_volume, smooth_area = _smooth_volume_area(vertex_arrays, face_arrays, volume, mesh_area)
    return volume, smooth_area * (volume / smooth_volume) ** (2 / 3), centroid, moment


def bubble_sizes(meshes):
    """Volume, surface area and centroid of many bubbles (the module docstring's definitions).

    The ``volume_mm3``, ``surface_area_mm2`` and ``centroid_x|y|z_mm`` of both ``bubsub reconstruct``'s
    and ``bubsub analyse``'s ``bubbles.csv`` (the same numbers, to the bit).

    Parameters
    ----------
    meshes : sequence of Mesh
        Closed, outward (the refined bubble surfaces).

    Returns
    -------
    volume : (n,) float
        mm^3, of the solid the mesh encloses.
    area : (n,) float
        mm^2, of the smooth surface at that volume.
    centroid : (n, 3) float
        mm, of the solid.
    """
    meshes = list(meshes)
    if not meshes:
        return np.zeros(0), np.zeros(0), np.zeros((0, 3))
    volume, area, centroid, _ = _checked_moments(meshes)
    return volume, area, centroid


def bubble_table(items, ids=None):
    """Per-bubble measurements.

    Parameters
    ----------
    items : sequence of Mesh or of Polygon (or SubdivisionSurface, measured refined)
    ids : sequence of int, optional
        Default ``0..n-1``.

    Returns
    -------
    list of dict
        2D rows have :data:`BUBBLE_COLUMNS_2D` (``equivalent_diameter_mm =
        2 sqrt(area / pi)``); 3D rows have :data:`BUBBLE_COLUMNS_3D`
        (``equivalent_diameter_mm = (6 volume / pi)^(1/3)``; the surface area
        of :func:`bubble_sizes`, as ``bubsub analyse``); units and meanings in :data:`BUBBLE_COLUMN_INFO`.
    """
    if isinstance(items, (Mesh, Polygon)) or hasattr(items, "fine"):
        items = [items]
    items = list(items)
    resolved = [it.fine() if not isinstance(it, (Mesh, Polygon)) and hasattr(it, "fine") else it for it in items]
    if not resolved:
        return []
    if all(isinstance(it, Polygon) for it in resolved):
        want = Polygon
    elif all(isinstance(it, Mesh) for it in resolved):
        want = Mesh
    else:
        kinds = sorted({type(it).__name__ for it in resolved})
        raise ValueError(f"items must be all Mesh or all Polygon, got {kinds}")
    resolved = resolve_items(resolved, want, "items")
    bid = bubble_ids(ids, len(resolved))
    rows = []
    if want is Mesh:
        volume, area, centroid = bubble_sizes(resolved)
        for i, v, a, c in zip(bid, volume, area, centroid):
            values = (c[0], c[1], c[2], v, a, 2.0 * equivalent_radius(v, 3))
            rows.append(dict(zip(BUBBLE_COLUMNS_3D, (i, *map(float, values)))))
        return rows
    for i, it in zip(bid, resolved):
        c = np.asarray(it.centroid, dtype=float)
        values = (c[0], c[1], it.area, it.perimeter, 2.0 * it.equivalent_radius)
        rows.append(dict(zip(BUBBLE_COLUMNS_2D, (i, *map(float, values)))))
    return rows


def thomsen_area(semi_axes, p=THOMSEN_P):
    """Knud Thomsen's approximate ellipsoid area (FoamQuant's), mm^2.

    Parameters
    ----------
    semi_axes : (..., 3) float
    p : float
        1.6 (FoamQuant), or 1.6075 for the smallest largest error (about 1 %).
    """
    a = np.asarray(semi_axes, dtype=float) ** p
    return 4.0 * np.pi * ((a[..., 0] * a[..., 1] + a[..., 0] * a[..., 2] + a[..., 1] * a[..., 2]) / 3.0) ** (1.0 / p)


def _sphericity(volume, area):
    return np.pi ** (1 / 3) * (6.0 * volume) ** (2 / 3) / area


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
    volume, _, centroid, tensor = _moments([vertices], [faces])
    return float(volume[0]), centroid[0], tensor[0] * volume[0]


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


def bubble_shapes(meshes):
    """The shape quantities of many bubbles at once (see the module docstring).

    All meshes' tetrahedra are summed in one pass (:func:`_moments`), so a
    foam of hundreds of bubbles costs a few array operations rather than
    hundreds.

    Parameters
    ----------
    meshes : sequence of Mesh
        Closed, outward (the refined bubble surfaces).

    Returns
    -------
    list of dict
        Keys of :data:`SHAPE_COLUMNS`; ``axis_i_x|y|z`` are the unit eigenvectors of the
        shape tensor, ``i = 1`` the longest.

    Raises
    ------
    ValueError
        If a mesh encloses a non-positive volume.
    """
    meshes = list(meshes)
    if not meshes:
        return []
    volume, area, centroid, moment = _checked_moments(meshes)
    lam, vec = np.linalg.eigh(moment)
    lam, vec = lam[:, ::-1], vec[:, :, ::-1]
    semi = np.sqrt(5.0 * np.maximum(lam, 0.0))
    sphericity_ellipsoid = _sphericity(4 / 3 * np.pi * semi.prod(axis=1), thomsen_area(semi))
    rows = []
    for k in range(len(meshes)):
        axes = _axis_sign(vec[k])
        row = {"centroid_x_mm": centroid[k, 0], "centroid_y_mm": centroid[k, 1], "centroid_z_mm": centroid[k, 2],
               "volume_mm3": volume[k], "surface_area_mm2": area[k],
               "equivalent_diameter_mm": 2.0 * equivalent_radius(volume[k], 3),
               "sphericity": _sphericity(volume[k], area[k]),
               "sphericity_ellipsoid": sphericity_ellipsoid[k] if np.all(semi[k] > 0) else np.nan}
        for i in range(3):
            row[f"shape_eigenvalue_{i + 1}_mm2"] = lam[k, i]
        for i in range(3):
            row[f"semi_axis_{i + 1}_mm"] = semi[k, i]
        for i in range(3):
            for j, name in enumerate("xyz"):
                row[f"axis_{i + 1}_{name}"] = axes[j, i]
        if np.all(semi[k] > 0):
            u, vm, kind = strain_from_axes(semi[k])
        else:  # a flat (degenerate) bubble has no finite strain
            u, vm, kind = np.full(3, np.nan), np.nan, 0
        for i in range(3):
            row[f"strain_{i + 1}"] = u[i]
        row["strain_von_mises"] = vm
        rows.append({key: (float(val) if key != "shape_type" else val) for key, val in row.items()})
        rows[-1]["shape_type"] = int(kind)
    return rows


def bubble_shape(mesh):
    """:func:`bubble_shapes` of one mesh (a dict)."""
    return bubble_shapes([mesh])[0]


#: ``column: (unit, meaning)`` of the shape columns of ``bubbles.csv`` (those ``bubsub reconstruct``'s
#: ``bubbles.csv`` has too in its words, :data:`bubsub.core.io.columns.BUBBLE_COLUMN_INFO`).
SHAPE_COLUMN_INFO = {
    **{c: BUBBLE_COLUMN_INFO[c] for c in ("centroid_x_mm", "centroid_y_mm", "centroid_z_mm", "volume_mm3",
                                         "surface_area_mm2", "equivalent_diameter_mm")},
    "sphericity": ("1", "pi^(1/3) (6 V)^(2/3) / A of the smooth surface: 1 for a ball, less for any other shape"),
    "sphericity_ellipsoid": ("1", "sphericity of the ellipsoid of the same shape tensor, Thomsen's area with p = 1.6 "
                                  "(FoamQuant RegionProp)"),
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
