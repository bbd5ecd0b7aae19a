"""One foam at one time: the bubble, contact and region tables from the bubbles' fine meshes.

:func:`analyse_meshes` is the Python API of ``bubsub analyse`` for one
reconstruction: shape per bubble (:mod:`~bubsub.core.analysis.shape`),
contacts and coordination (:mod:`~bubsub.core.analysis.contacts`), liquid
fraction and texture per region (:mod:`~bubsub.core.analysis.regions`).

Bubbles cut by the field of view (``truncated``) keep their row, centroid,
coordination and the volume inside the field of view; their whole-size and
shape columns are left empty, as in ``bubsub reconstruct``'s ``bubbles.csv``,
and they are left out of every statistic.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from bubsub.core.analysis.contacts import CONTACT_COLUMN_INFO, Surface, find_contacts
from bubsub.core.analysis.dynamics import Step
from bubsub.core.analysis.regions import GRID_COLUMN_INFO, SHELL_COLUMN_INFO, Domain, region_tables
from bubsub.core.analysis.shape import SHAPE_COLUMN_INFO, bubble_shapes
from bubsub.core.io import tables

__all__ = ["Snapshot", "analyse_meshes", "BUBBLE_COLUMN_INFO", "SNAPSHOT_TABLES", "default_regions"]

#: Shape columns a truncated bubble leaves empty (its whole shape is not a measurement).
WHOLE_SHAPE = tuple(c for c in SHAPE_COLUMN_INFO if not c.startswith("centroid_"))

#: ``column: (unit, meaning)`` of the analysis' ``bubbles.csv`` (the columns ``bubsub reconstruct``'s has too
#: in its words, :data:`bubsub.core.io.tables.BUBBLE_COLUMN_INFO` and ``FOV_COLUMN_INFO``).
BUBBLE_COLUMN_INFO = {
    "id": tables.BUBBLE_COLUMN_INFO["id"],
    **SHAPE_COLUMN_INFO,
    "coordination": ("1", "number of contacts (bubbles whose surface comes closer than the contact gap)"),
    "truncated": tables.FOV_COLUMN_INFO["truncated"],
    "volume_in_fov_mm3": tables.FOV_COLUMN_INFO["volume_in_fov_mm3"],
}


@dataclass
class Snapshot:
    """The analysis of one foam: tables as lists of rows (dicts) and a summary.

    Attributes
    ----------
    ids : list of int
    bubbles : list of dict
        Columns of :data:`BUBBLE_COLUMN_INFO`.
    contacts : list of dict
        Columns of :data:`~bubsub.core.analysis.contacts.CONTACT_COLUMN_INFO`.
    grid, shells : list of dict
        :func:`~bubsub.core.analysis.regions.region_tables`.
    summary : dict
        Counts, contact gap, mean coordination, liquid fraction, the regions' settings and the
        seconds each part took.
    """

    ids: list
    bubbles: list
    contacts: list
    grid: list
    shells: list
    summary: dict = field(default_factory=dict)

    def step(self, index, time_value):
        """This foam as one :class:`~bubsub.core.analysis.dynamics.Step` of a time series."""
        vol = np.array([np.nan if r["volume_mm3"] == "" else r["volume_mm3"] for r in self.bubbles], dtype=float)
        cen = np.array([[r[f"centroid_{a}_mm"] for a in "xyz"] for r in self.bubbles], dtype=float).reshape(-1, 3)
        pairs = frozenset((int(r["id_a"]), int(r["id_b"])) for r in self.contacts)
        return Step(int(index), float(time_value), np.array(self.ids, dtype=int), vol,
                    np.array([r["coordination"] for r in self.bubbles], dtype=int), cen, pairs)


def default_regions(radius, domain):
    """Default cells and shells for bubbles of median equivalent radius ``radius`` (mm).

    Cartesian cells about three bubble diameters wide, shells about one and a
    half diameters wide.

    Returns
    -------
    grid : (3,) int
    shells : int
    """
    size = np.asarray(domain.hi) - np.asarray(domain.lo)
    grid = tuple(int(max(1, round(s / (6.0 * radius)))) for s in size)
    shells = int(max(1, round(domain.outer_radius / (3.0 * radius))))
    return grid, shells


def _checked_flags(values, n, what):
    if values is None:
        return None
    a = np.asarray(values, dtype=float).reshape(-1)
    if len(a) != n:
        raise ValueError(f"{what} has {len(a)} entries but there are {n} bubbles")
    return a


def analyse_meshes(meshes, ids=None, *, contact_gap, field_of_view=None, truncated=None, volume_in_fov=None,
                   domain=None, domain_source=None, grid=None, shells=None):
    """Bubble, contact and region tables of one foam.

    Parameters
    ----------
    meshes : sequence of Mesh
        The bubbles' fine (refined) surfaces, closed and outward.
    ids : sequence of int, optional
        Bubble ids (default ``0..n-1``).
    contact_gap : float
        mm; bubbles whose surfaces come closer are in contact.
    field_of_view : (radius, half_height), optional
        mm, about the z axis; the regions' domain unless ``domain`` is given (default: the bubbles'
        bounding box).
    truncated : (n,) int, optional
        1 for bubbles cut by the field of view (their whole size is not measured).
    volume_in_fov : (n,) float, optional
        Their volume inside the field of view, mm^3.
    domain : Domain, optional
        The regions' domain: the sample (its liquid box or column) within the field of view, since
        liquid fractions count everything outside the bubbles as liquid.
    domain_source : str, optional
        Where ``domain`` comes from, for the summary (default: what this function chose).
    grid : (3,) int, optional
    shells : int, optional
        Regions' cells and shells; defaults of :func:`default_regions`.

    Returns
    -------
    Snapshot
    """
    meshes = list(meshes)
    n = len(meshes)
    if n == 0:
        raise ValueError("there are no bubbles to analyse")
    ids = list(range(n)) if ids is None else [int(i) for i in ids]
    if len(ids) != n or len(set(ids)) != n:
        raise ValueError(f"ids must be {n} distinct integers, got {len(ids)} ({len(set(ids))} distinct)")
    gap = float(contact_gap)
    if not (gap > 0 and np.isfinite(gap)):
        raise ValueError(f"the contact gap must be positive and finite, got {contact_gap!r} mm")
    flags = _checked_flags(truncated, n, "truncated")
    inside = _checked_flags(volume_in_fov, n, "volume_in_fov")
    seconds = {}
    t = time.perf_counter()
    shapes = bubble_shapes(meshes)
    seconds["shape"] = time.perf_counter() - t
    t = time.perf_counter()
    contacts = find_contacts([Surface.of(m) for m in meshes], gap)
    seconds["contacts"] = time.perf_counter() - t
    coordination = contacts.coordination(n)
    centroids = np.array([[s[f"centroid_{a}_mm"] for a in "xyz"] for s in shapes])
    cut = np.zeros(n, dtype=int) if flags is None else (flags > 0).astype(int)

    rows = []
    for k in range(n):
        row = {"id": ids[k], **shapes[k], "coordination": int(coordination[k])}
        row["truncated"] = "" if flags is None else int(cut[k])
        if inside is not None:
            row["volume_in_fov_mm3"] = float(inside[k])
        elif flags is not None and not cut[k]:
            row["volume_in_fov_mm3"] = shapes[k]["volume_mm3"]
        else:
            row["volume_in_fov_mm3"] = ""
        if cut[k]:
            for c in WHOLE_SHAPE:
                row[c] = ""
        rows.append(row)

    contact_rows = []
    branches = np.zeros((len(contacts), 3))
    for c, (i, j) in enumerate(contacts.pairs):
        if ids[i] > ids[j]:
            i, j = j, i
        b = centroids[j] - centroids[i]
        branches[c] = b
        row = {"id_a": ids[i], "id_b": ids[j], "gap_mm": float(contacts.gap[c])}
        row.update({f"contact_{a}_mm": float(contacts.point[c, k]) for k, a in enumerate("xyz")})
        row.update({f"branch_{a}_mm": float(b[k]) for k, a in enumerate("xyz")})
        row["branch_length_mm"] = float(np.linalg.norm(b))
        row["film_area_mm2"] = float(contacts.film_area[c])
        contact_rows.append(row)
    contact_rows.sort(key=lambda r: (r["id_a"], r["id_b"]))

    t = time.perf_counter()
    if domain is None:
        domain = Domain.field_of_view(*field_of_view) if field_of_view is not None else Domain.around(meshes)
        domain_source = domain_source or ("the field of view" if field_of_view is not None
                                          else "the bounding box of the bubbles")
    whole = cut == 0
    radius = 0.5 * float(np.median([s["equivalent_diameter_mm"] for s, w in zip(shapes, whole) if w] or
                                   [s["equivalent_diameter_mm"] for s in shapes]))
    g0, s0 = default_regions(radius, domain)
    grid = g0 if grid is None else tuple(int(g) for g in grid)
    shells = s0 if shells is None else int(shells)
    grid_rows, shell_rows = region_tables(meshes, centroids, coordination, cut, contacts, branches, domain,
                                          grid=grid, shells=shells)
    seconds["regions"] = time.perf_counter() - t
    total = sum(r["region_volume_mm3"] for r in grid_rows)
    gas = sum(r["gas_volume_mm3"] for r in grid_rows)
    sph = np.array([s["sphericity"] for s, w in zip(shapes, whole) if w])
    summary = {
        "bubbles": n, "bubbles_truncated": int(cut.sum()) if flags is not None else None,
        "contact_gap_mm": gap, "contacts": len(contacts),
        "mean_coordination": float(coordination[whole].mean()) if whole.any() else None,
        "median_equivalent_radius_mm": radius,
        "median_sphericity": float(np.median(sph)) if len(sph) else None,
        "liquid_fraction": float(1 - gas / total) if total else None,
        "domain": {**domain.describe(), "source": domain_source or "given"},
        "grid": list(grid), "shells": shells,
        "seconds": seconds,
    }
    return Snapshot(ids, rows, contact_rows, grid_rows, shell_rows, summary)


#: Tables of a :class:`Snapshot` with their column descriptions.
SNAPSHOT_TABLES = {"bubbles": BUBBLE_COLUMN_INFO, "contacts": CONTACT_COLUMN_INFO, "grid": GRID_COLUMN_INFO,
                   "shells": SHELL_COLUMN_INFO}
