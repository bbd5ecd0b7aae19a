"""Tables (CSV) whose columns carry their units, with a CSV-on-the-Web sidecar; the bubble table.

Every column name ends with its unit (:func:`unit_column`: ``volume_mm3``,
``centroid_x_mm``), and :func:`write_csv` can write a sidecar
``NAME.csv-metadata.json`` (W3C CSV on the Web metadata) giving each
column's unit and meaning. :func:`bubble_table` measures bubbles:
``id, centroid_x_mm, centroid_y_mm[, centroid_z_mm], area_mm2 | volume_mm3,
perimeter_mm | surface_area_mm2, equivalent_diameter_mm``.

Every writer is atomic (:mod:`bubsub.core.io.atomic`). Floats are written
as ``repr`` (they read back exactly).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from bubsub.core.io.atomic import atomic_open
from bubsub.core.projection.items import bubble_ids, resolve_items
from bubsub.core.projection.mesh import Mesh, Polygon

__all__ = [
    "UNIT_SUFFIXES",
    "unit_column",
    "bubble_table",
    "write_csv",
    "csv_metadata_path",
    "BUBBLE_COLUMNS_2D",
    "BUBBLE_COLUMNS_3D",
    "BUBBLE_COLUMN_INFO",
]

#: How a unit is written at the end of a column name (``volume`` in mm^3 is ``volume_mm3``).
UNIT_SUFFIXES = {"": "", "mm": "mm", "mm^2": "mm2", "mm^3": "mm3", "1/mm": "per_mm", "s": "s", "deg": "deg",
                 "subscan": "subscan", "1": ""}


def unit_column(quantity, unit):
    """A column name that carries its unit: ``unit_column("volume", "mm^3") == "volume_mm3"``.

    Parameters
    ----------
    quantity : str
        E.g. ``"centroid_x"``.
    unit : str
        One of :data:`UNIT_SUFFIXES` (``""`` or ``"1"`` for counts, ids and
        other dimensionless columns, which keep their bare name).

    Returns
    -------
    str
    """
    if unit not in UNIT_SUFFIXES:
        raise ValueError(f"unknown unit {unit!r}; known: {sorted(UNIT_SUFFIXES)}")
    suffix = UNIT_SUFFIXES[unit]
    return f"{quantity}_{suffix}" if suffix else quantity


#: ``column name: (unit, meaning)`` of every column :func:`bubble_table` writes.
BUBBLE_COLUMN_INFO = {
    "id": ("", "bubble id (the bubble_id of the PLY faces / the id of the JSON polygon)"),
    **{unit_column(f"centroid_{a}", "mm"): ("mm", f"{a} coordinate of the centroid of the refined surface")
       for a in "xyz"},
    unit_column("area", "mm^2"): ("mm^2", "area enclosed by the refined 2D outline"),
    unit_column("perimeter", "mm"): ("mm", "length of the refined 2D outline"),
    unit_column("volume", "mm^3"): ("mm^3", "volume enclosed by the refined 3D surface"),
    unit_column("surface_area", "mm^2"): ("mm^2", "area of the refined 3D surface"),
    unit_column("equivalent_diameter", "mm"): (
        "mm", "diameter of the disc (2D) or ball (3D) of the same area (volume)"),
}

#: Columns of :func:`bubble_table` for 2D bubbles.
BUBBLE_COLUMNS_2D = ("id", "centroid_x_mm", "centroid_y_mm", "area_mm2", "perimeter_mm", "equivalent_diameter_mm")
#: Columns of :func:`bubble_table` for 3D bubbles.
BUBBLE_COLUMNS_3D = ("id", "centroid_x_mm", "centroid_y_mm", "centroid_z_mm", "volume_mm3", "surface_area_mm2",
                     "equivalent_diameter_mm")


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
        (``equivalent_diameter_mm = (6 volume / pi)^(1/3)``); units and
        meanings in :data:`BUBBLE_COLUMN_INFO`.
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
    for i, it in zip(bid, resolved):
        c = np.asarray(it.centroid, dtype=float)
        if want is Polygon:
            a = float(it.area)
            values = (i, c[0], c[1], a, it.perimeter, 2.0 * it.equivalent_radius)
            rows.append(dict(zip(BUBBLE_COLUMNS_2D, (i, *map(float, values[1:])))))
        else:
            v = float(it.volume)
            values = (c[0], c[1], c[2], v, it.area, 2.0 * it.equivalent_radius)
            rows.append(dict(zip(BUBBLE_COLUMNS_3D, (i, *map(float, values)))))
    return rows


def csv_metadata_path(path):
    """The sidecar of a CSV file: ``bubbles.csv`` -> ``bubbles.csv-metadata.json`` (the CSVW convention)."""
    p = Path(path)
    return p.with_name(p.name + "-metadata.json")


def _csv_metadata(path, columns, info, title):
    cols = []
    for c in columns:
        if c not in info:
            raise ValueError(f"column {c!r} has no (unit, meaning) in the column descriptions")
        unit, meaning = info[c]
        entry = {"name": c, "titles": c, "dc:description": meaning}
        if unit:
            entry["unit"] = unit
        cols.append(entry)
    doc = {"@context": "http://www.w3.org/ns/csvw", "url": Path(path).name, "dc:title": title,
           "dialect": {"header": True}, "tableSchema": {"columns": cols}}
    return json.dumps(doc, indent=2) + "\n"


def write_csv(path, rows, columns=None, *, describe=None, title=None):
    """Write rows (dicts) as CSV with a header line, atomically, and optionally its column sidecar.

    Parameters
    ----------
    path : str or os.PathLike
    rows : sequence of dict
        All with the same keys.
    columns : sequence of str, optional
        Column order; defaults to the keys of the first row. With no rows
        and no columns, an empty file is written.
    describe : dict, optional
        ``{column: (unit, meaning)}`` for every column (e.g.
        :data:`BUBBLE_COLUMN_INFO`); then the sidecar
        :func:`csv_metadata_path` is written too (W3C CSV on the Web
        metadata: name, unit, description of each column).
    title : str, optional
        Title of the table in the sidecar.

    Returns
    -------
    pathlib.Path
    """
    rows = list(rows)
    if columns is None:
        columns = list(rows[0].keys()) if rows else []
    columns = [str(c) for c in columns]
    for k, r in enumerate(rows):
        if not isinstance(r, dict):
            raise ValueError(f"rows[{k}] is not a dict")
        if set(r) != set(columns):
            missing = sorted(set(columns) - set(r))
            extra = sorted(set(r) - set(columns))
            raise ValueError(f"rows[{k}] keys differ from the columns (missing {missing}, extra {extra})")
    # described before anything is written, so an undescribed column writes neither file
    meta = None if describe is None else _csv_metadata(path, columns, describe, title or Path(path).stem)
    with atomic_open(path, "w", newline="") as fh:
        if columns:
            w = csv.DictWriter(fh, fieldnames=columns, lineterminator="\n")
            w.writeheader()
            for r in rows:
                w.writerow({k: (repr(float(v)) if isinstance(v, (float, np.floating)) else v) for k, v in r.items()})
    if meta is not None:
        with atomic_open(csv_metadata_path(path), "w") as fh:
            fh.write(meta)
    return Path(path)
