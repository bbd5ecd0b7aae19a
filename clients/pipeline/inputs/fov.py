"""The field of view: the region every projection sees, and bubbles cut by its edge.

Real scans cut bubbles: the detector's top and bottom, and the cylinder
(disc in 2D) outside which a point leaves the detector at some angles.

* :func:`field_of_view`, :func:`inside_fov`, :func:`fov_mask`: that region.
* :func:`seen_by`: how many projections see a point; :func:`unobserved_control`:
  control vertices no ray sees (the fit leaves them where they started).
* :func:`truncated_flags` (with :func:`reaches_edge_rows`, the detector's top and bottom), :func:`size_inside_fov`,
  :func:`fov_columns`: the ``bubbles.csv`` columns of cut bubbles (flag, measured part, whole size left empty).
* :func:`preview_extension`: the preview beyond the field of view's cylinder
  where the data show bubbles there (the field-of-view model,
  ``ReconstructionSettings(fov_model=True)``, the default; ``--no-fov-model``
  switches it off).

The model's other parts live where they act: the edge rows' seeds
(:func:`bubsub.clients.pipeline.static.initial.edge_slices`), the topology rules at
the edge (:mod:`bubsub.clients.pipeline.static.topology`), the unseen parts'
continuation (:func:`bubsub.clients.pipeline.static.repair.continued`) and the
check of what the detector's sides show
(:func:`bubsub.clients.pipeline.inputs.sides.check_lateral_truncation`: a foam
wider than the detector, local tomography, is reconstructed with a note).
Measured with and without the model: docs/prepare.md, ``python -m
bubsub.bench fov``; local tomography: ``python -m bubsub.bench fov --local``.

Local tomography: the bubbles out to :data:`LOCAL_EXTEND` times the field
of view's radius are fitted where the views constrain them, and the gas
beyond (seen in fewer than 46 % of a 180-degree scan's projections at 1.5
times the radius) is left to the fit's residual, less what every projection
shares (:mod:`bubsub.clients.pipeline.static.detector_term`, fitted where
:func:`local_tomography` holds).
"""

from __future__ import annotations

import numpy as np

from bubsub.clients.pipeline.inputs.sides import LOCAL_VIEWS, side_bubble_signal, side_signal
from bubsub.core.io.tables import FOV_COLUMN_INFO
from bubsub.core.projection.mesh import volume_in_slab
from bubsub.core.projection.masks import coverage, pixel_centres

__all__ = ["field_of_view", "fov_report", "local_tomography", "sides_clear", "truncated_flags", "reaches_edge_rows",
           "TRUNCATED_INFO", "inside_fov", "preview_extension", "FOV_EXTEND", "LOCAL_EXTEND", "seen_by",
           "unobserved_control", "size_inside_fov", "fov_columns", "FOV_COLUMN_INFO", "WHOLE_SIZE_COLUMNS",
           "fov_mask"]

#: Radius of the voxel preview's grid over the field of view's radius when the boundary is modelled: a point
#: at 1.25 times the radius of a 180-degree parallel scan is still seen by 59 % of the projections.
FOV_EXTEND = 1.25
#: The same for local tomography (the bubbles' signal at a detector side in most projections,
#: :func:`bubsub.clients.pipeline.inputs.sides.check_lateral_truncation`): against 1.6 (every bubble of a foam 1.5
#: times the field of view's radius modelled) it finds the same interior bubbles at nearly the same DDI for
#: less work (``python -m bubsub.bench fov --local-ideal 0 --local-extend 1.25 1.6``, docs/prepare.md).
LOCAL_EXTEND = FOV_EXTEND


def preview_extension(fov_model, data=None, contrast=None):
    """Factor by which the voxel preview's grid radius exceeds the field of view's.

    :data:`FOV_EXTEND` with the model (:data:`LOCAL_EXTEND` for a foam wider
    than the detector), 1 without it, and 1 as well when
    ``data`` show that nothing lies outside the field of view's cylinder: in
    every projection both sides of the detector see no bubble signal
    (:func:`bubsub.clients.pipeline.inputs.sides.side_signal`), so each view's
    shadow of the sample lies within the detector and the sample within the
    cylinder (the common case of a column narrower than the detector; the
    wider grid would only add 56 % to the preview's voxels).

    Parameters
    ----------
    fov_model : bool
    data : ndarray, optional
        The fitted projections' bubble signal (``data - background``),
        ``(views, cols)`` or ``(views, rows, cols)``.
    contrast : float, optional
        Bubble contrast (its sign makes the signal positive); needed with ``data``.
    """
    if not fov_model:
        return 1.0
    if data is None:
        return FOV_EXTEND
    case = _sides(data, contrast)
    return 1.0 if case is None else LOCAL_EXTEND if case else FOV_EXTEND


def _sides(data, contrast):
    """None when neither side of the detector sees bubble signal in any projection, else whether it
    sees the bubbles' signal in at least :data:`LOCAL_VIEWS` of them (local tomography)."""
    left, right, level = side_signal(np.sign(contrast) * np.asarray(data, dtype=np.float32))
    if not bool(np.any(left > level) or np.any(right > level)):
        return None
    left, right, level = side_bubble_signal(data, contrast)
    return max(np.count_nonzero(left > level), np.count_nonzero(right > level)) >= LOCAL_VIEWS * len(left)


def sides_clear(data, contrast):
    """Whether neither side of the detector sees bubble signal in any projection: each view's shadow of the
    bubbles lies within the detector (``data``, ``contrast`` as :func:`local_tomography`'s)."""
    return _sides(data, contrast) is None


def local_tomography(data, contrast):
    """Whether the bubbles' signal reaches a side of the detector in at least :data:`LOCAL_VIEWS` of
    the projections: a foam wider than the detector, as :func:`preview_extension` judges it.

    Parameters
    ----------
    data : ndarray
        Bubble signal (``data - background``), ``(views, cols)`` or ``(views, rows, cols)``.
    contrast : float
        Bubble contrast.

    Returns
    -------
    bool
    """
    return bool(_sides(data, contrast))


def field_of_view(geometry):
    """Half-sizes of the region every projection sees: ``(r_xy, half_z)`` in mm.

    For circular scans this is the radius of the reconstructable disc
    (detector half-width divided by the magnification) and, in 3D, half the
    detector height likewise.
    """
    g = geometry
    n = g.ndim
    vec = g.vectors
    s, d, u = vec[:, :n], vec[:, n:2 * n], vec[:, 2 * n:3 * n]
    # a detector shifted along u (an off-centre rotation axis) sees less on one side
    shift = np.abs(np.einsum("ij,ij->i", d, u)) / np.linalg.norm(u, axis=1)
    half_w = 0.5 * g.det_cols * np.linalg.norm(u, axis=1) - shift
    if g.is_cone:
        mag = np.linalg.norm(s - d, axis=1) / np.linalg.norm(s, axis=1)
    else:
        mag = np.ones(len(vec))
    r_xy = float(np.min(half_w / mag))
    if n == 2:
        return r_xy, 0.0
    half_h = 0.5 * g.det_rows * np.linalg.norm(vec[:, 9:12], axis=1)
    return r_xy, float(np.min(half_h / mag))


#: Unit and meaning of the ``truncated`` column of ``bubbles.csv``.
TRUNCATED_INFO = FOV_COLUMN_INFO["truncated"]


def fov_report(geometry):
    r_xy, half_z = field_of_view(geometry)
    n = geometry.ndim
    pixel = float(np.linalg.norm(geometry.vectors[0, 2 * n:3 * n]))
    return {"radius": r_xy, "half_height": half_z, "margin": pixel}


def truncated_flags(items, fov, margin):
    """1 for each bubble that reaches the edge of the field of view, else 0.

    Parameters
    ----------
    items : sequence of Polygon or Mesh
        Refined bubbles.
    fov : (r_xy, half_z)
        :func:`field_of_view`, mm (``half_z`` ignored in 2D).
    margin : float
        A bubble within this distance (mm) of the edge counts as reaching it.
    """
    r_xy, half_z = fov
    flags = []
    for it in items:
        v = np.asarray(it.vertices, dtype=float)
        flags.append(int(np.hypot(v[:, 0], v[:, 1]).max() > r_xy - margin or reaches_edge_rows(v, half_z, margin)))
    return flags


def reaches_edge_rows(vertices, half_z, margin=0.0):
    """Whether a 3D bubble's vertices reach the detector's top or bottom edge plane (within ``margin``, mm); False
    in 2D.

    Parameters
    ----------
    vertices : (n, 2) or (n, 3) float
        mm.
    half_z : float
        :func:`field_of_view`'s half height, mm.
    margin : float
        mm.
    """
    v = np.asarray(vertices, dtype=float)
    return bool(v.shape[1] == 3 and np.abs(v[:, 2]).max() > half_z - margin)




def inside_fov(points, fov, margin=0.0):
    """Whether points lie inside the field of view (shrunk by ``margin``).

    Parameters
    ----------
    points : (n, 2) or (n, 3) float
        mm.
    fov : (r_xy, half_z)
        :func:`field_of_view`, mm (``half_z`` ignored for 2D points).
    margin : float
        mm.

    Returns
    -------
    (n,) bool
    """
    p = np.asarray(points, dtype=float)
    r_xy, half_z = fov
    ok = np.hypot(p[:, 0], p[:, 1]) <= r_xy - margin
    if p.shape[1] == 3:
        ok &= np.abs(p[:, 2]) <= half_z - margin
    return ok


def seen_by(points, geometry):
    """How many projections see each point (its ray lands on the detector).

    Parameters
    ----------
    points : (n, ndim) float
        mm, ``ndim`` that of the geometry.
    geometry : ScanGeometry

    Returns
    -------
    (n,) int
        0 for a point no ray of the data crosses (above the detector's top
        in a parallel scan, say); ``geometry.n_angles`` inside the field of view.
    """
    g = geometry
    col, row, ahead = g.detector_coordinates(points)
    ok = ahead & (np.abs(col) <= 0.5 * g.det_cols)
    if g.ndim == 3:
        ok &= np.abs(row) <= 0.5 * g.det_rows
    return ok.sum(axis=0)


def unobserved_control(surface, geometry):
    """Control vertices whose refined neighbourhood no ray of the data sees.

    The objective's gradient with respect to such a vertex is zero, and
    BFGS (as L-BFGS) moves only along combinations of past gradients and
    their differences, so the fit leaves these vertices exactly where they
    started: the unseen part of a bubble keeps its initial (spherical)
    shape instead of drifting, and the validity step then continues it from
    the fitted visible part (:func:`bubsub.clients.pipeline.static.repair.continued`).
    They are reported, not measured.

    Parameters
    ----------
    surface : SubdivisionSurface
    geometry : ScanGeometry

    Returns
    -------
    (n_control,) bool
    """
    seen = seen_by(surface.fine().vertices, geometry) > 0
    support = abs(surface.S).T @ seen.astype(float)
    return np.asarray(support).ravel() == 0


def size_inside_fov(item, fov, *, samples=48):
    """Area (2D) or volume (3D) of a bubble's part inside the field of view.

    A 3D bubble that the detector's top or bottom cut, and not the field of
    view's cylinder, is clipped by the two planes exactly
    (:func:`~bubsub.core.projection.mesh.volume_in_slab`; a hundredth of the
    grid's time, which a 4D run spends on every cut bubble of every
    subscan). Others are rasterised on a grid of ``samples`` cells across
    the bubble's bounding box, two sub-samples per cell and axis, with cell
    faces on the detector's nearer edge plane (error well under 1 % of the
    bubble's size for round bubbles).

    Parameters
    ----------
    item : Polygon or Mesh (refined bubble)
    fov : (r_xy, half_z)
        mm.

    Returns
    -------
    float
        mm^2 or mm^3.
    """
    v = np.asarray(item.vertices, dtype=float)
    ndim = v.shape[1]
    if ndim == 3 and np.all(np.hypot(v[:, 0], v[:, 1]) <= fov[0]):
        return volume_in_slab(v, item.faces, -fov[1], fov[1])
    lo, hi = v.min(axis=0), v.max(axis=0)
    h = float((hi - lo).max()) / samples
    lo, hi = lo - h, hi + h
    if ndim == 3:  # voxel faces on the nearer of the detector's top and bottom planes: no half-voxel bias there
        plane = fov[1] if lo[2] + hi[2] > 0 else -fov[1]
        lo[2] = plane - np.ceil((plane - lo[2]) / h) * h
    shape = tuple(int(np.ceil((hi[k] - lo[k]) / h)) for k in reversed(range(ndim)))
    extent = tuple(x for k in range(ndim) for x in (lo[k], lo[k] + shape[ndim - 1 - k] * h))
    frac = coverage(item, shape, extent, supersample=2)
    return float(frac[fov_mask(shape, extent, fov)].sum() * h ** ndim)


def fov_mask(shape, extent, fov):
    """Which pixels (voxels) of a grid have their centre inside the field of view.

    Parameters
    ----------
    shape : (rows, cols) or (slices, rows, cols)
    extent : (xmin, xmax, ymin, ymax[, zmin, zmax])
        mm (grid convention of :mod:`bubsub.core.projection.masks`).
    fov : (r_xy, half_z)

    Returns
    -------
    bool ndarray, ``shape``
    """
    axes = np.meshgrid(*pixel_centres(shape, extent), indexing="ij")  # (y, x) or (z, y, x)
    points = np.stack([a.ravel() for a in reversed(axes)], axis=1)
    return inside_fov(points, fov).reshape(shape)


# FOV_COLUMN_INFO (``bubbles.csv`` columns added by :func:`fov_columns`: name -> (unit, meaning)) is
# bubsub.core.io.tables', which the analysis' tables share.

#: Size columns left empty for a truncated bubble: its whole size is not a measurement.
WHOLE_SIZE_COLUMNS = ("area_mm2", "perimeter_mm", "volume_mm3", "surface_area_mm2", "equivalent_diameter_mm")


def fov_columns(rows, items, report):
    """Add the field-of-view columns to ``bubbles.csv`` rows, in place.

    Each row gets ``truncated``, the size inside the field of view
    (``area_in_fov_mm2`` or ``volume_in_fov_mm3``) and, when the report
    lists them, ``unobserved_control_vertices``; a truncated bubble's
    whole-size columns (:data:`WHOLE_SIZE_COLUMNS`) are emptied.

    Parameters
    ----------
    rows : list of dict
        :func:`bubsub.core.analysis.shape.bubble_table` of ``items``.
    items : list of Polygon or Mesh
        Refined bubbles.
    report : dict
        ``report.json`` of the reconstruction: ``field_of_view_mm``
        (:func:`fov_report`) and optionally ``unobserved_control_vertices``
        (one count per bubble).

    Returns
    -------
    columns : tuple of str
        The names added, in order.
    """
    fovr = report["field_of_view_mm"]
    fov = (fovr["radius"], fovr["half_height"])
    three_d = bool(items) and np.asarray(items[0].vertices).shape[1] == 3
    size, whole = ("volume_in_fov_mm3", "volume_mm3") if three_d else ("area_in_fov_mm2", "area_mm2")
    unobserved = report.get("unobserved_control_vertices")
    if unobserved is not None and len(unobserved) != len(items):
        unobserved = None
    for k, (row, item, flag) in enumerate(zip(rows, items, truncated_flags(items, fov, fovr["margin"]))):
        row["truncated"] = flag
        row[size] = size_inside_fov(item, fov) if flag else row[whole]
        if unobserved is not None:
            row["unobserved_control_vertices"] = int(unobserved[k])
        if flag:
            for c in WHOLE_SIZE_COLUMNS:
                if c in row:
                    row[c] = ""
    return ("truncated", size) + (("unobserved_control_vertices",) if unobserved is not None else ())
