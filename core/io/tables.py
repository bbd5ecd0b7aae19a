"""Tables (CSV) whose columns carry their units, each with its CSV-on-the-Web sidecar; the bubble table's columns.

Every table bubsub writes goes through :func:`write_table`, the one place
that decides how a table is written:

* column names end with their unit (:func:`unit_column`: ``volume_mm3``,
  ``centroid_x_mm``);
* floats carry :data:`SIGNIFICANT_DIGITS` significant digits
  (:func:`format_cell`), integers and text as they are;
* an unknown or unmeasured value (None or NaN) is an empty cell, in every
  table (never ``nan``);
* beside ``NAME.csv`` the sidecar ``NAME.csv-metadata.json`` (W3C CSV on the
  Web metadata, :func:`csv_metadata_path`) gives each column's unit, meaning
  and datatype, says that empty cells are unknowns (``"null": ""``) and how
  many significant digits the numbers carry.

A new table needs only its rows and ``{column: (unit, meaning)}``::

    write_table(out / "lineage.csv", rows, LINEAGE_COLUMN_INFO, title="bubble lineage")

and :func:`markdown_columns` gives the same descriptions as the docs' column
table (``tests/test_tables.py`` checks that the docs list every column of
bubsub's tables so).

The bubble table's columns are :data:`BUBBLE_COLUMNS_2D` and
:data:`BUBBLE_COLUMNS_3D`: ``id, centroid_x_mm, centroid_y_mm[,
centroid_z_mm], area_mm2 | volume_mm3, perimeter_mm | surface_area_mm2,
equivalent_diameter_mm``; its rows are measured by
:func:`bubsub.core.analysis.shape.bubble_table`, with the analysis'
definitions, so a bubble has the same values in ``bubsub reconstruct``'s and
``bubsub analyse``'s ``bubbles.csv``.

Every writer is atomic (:mod:`bubsub.core.io.atomic`).
"""

from __future__ import annotations

import csv
import json
import math
import numbers
from pathlib import Path

import numpy as np

from bubsub.core.io.atomic import atomic_open
from bubsub.core.io.columns import BUBBLE_COLUMN_INFO, FOV_COLUMN_INFO, UNIT_SUFFIXES, unit_column

__all__ = [
    "UNIT_SUFFIXES",
    "SIGNIFICANT_DIGITS",
    "unit_column",
    "format_cell",
    "write_table",
    "write_csv",
    "markdown_columns",
    "csv_metadata_path",
    "BUBBLE_COLUMNS_2D",
    "BUBBLE_COLUMNS_3D",
    "BUBBLE_COLUMN_INFO",
    "FOV_COLUMN_INFO",
]

#: Significant digits of every float in a bubsub table (0.1 um on a 100 mm coordinate; relative 5e-6).
SIGNIFICANT_DIGITS = 6


#: Columns of :func:`bubsub.core.analysis.shape.bubble_table` for 2D bubbles.
BUBBLE_COLUMNS_2D = ("id", "centroid_x_mm", "centroid_y_mm", "area_mm2", "perimeter_mm", "equivalent_diameter_mm")
#: Columns of :func:`bubsub.core.analysis.shape.bubble_table` for 3D bubbles.
BUBBLE_COLUMNS_3D = ("id", "centroid_x_mm", "centroid_y_mm", "centroid_z_mm", "volume_mm3", "surface_area_mm2",
                     "equivalent_diameter_mm")


def markdown_columns(columns):
    """The columns of a table as a Markdown table (``| column | unit | meaning |``), for the docs.

    Parameters
    ----------
    columns : dict
        ``{column: (unit, meaning)}``, as :func:`write_table` takes.

    Returns
    -------
    str
        One line per column after the header, ending with a newline.
    """
    lines = ["| column | unit | meaning |", "|---|---|---|"]
    for name, (unit, meaning) in columns.items():
        lines.append(f"| `{name}` | {unit} | {meaning.replace('|', chr(92) + '|')} |")
    return "\n".join(lines) + "\n"


def csv_metadata_path(path):
    """The sidecar of a CSV file: ``bubbles.csv`` -> ``bubbles.csv-metadata.json`` (the CSVW convention)."""
    p = Path(path)
    return p.with_name(p.name + "-metadata.json")


def format_cell(value, digits=SIGNIFICANT_DIGITS):
    """One CSV cell: floats with ``digits`` significant digits, None and NaN empty, anything else as text.

    Parameters
    ----------
    value : object
    digits : int

    Returns
    -------
    str or int
        ``""`` for None and NaN; ``"inf"`` / ``"-inf"`` for infinities.
    """
    if value is None:
        return ""
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        v = float(value)
        if math.isnan(v):
            return ""
        return f"{v:.{int(digits)}g}"
    return value


def _datatype(values):
    """The CSVW datatype of a column's non-empty values."""
    present = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v)) and v != ""]
    if not present:
        return "string"
    if all(isinstance(v, (bool, np.bool_)) for v in present):
        return {"base": "boolean", "format": "True|False"}
    if all(isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_)) for v in present):
        return "integer"
    if all(isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)) for v in present):
        return "number"
    return "string"


def _csv_metadata(path, columns, info, title, rows, digits):
    cols = []
    for c in columns:
        if c not in info:
            raise ValueError(f"column {c!r} has no (unit, meaning) in the column descriptions")
        unit, meaning = info[c]
        entry = {"name": c, "titles": c, "dc:description": meaning, "datatype": _datatype([r[c] for r in rows])}
        if unit:
            entry["unit"] = unit
        cols.append(entry)
    doc = {"@context": "http://www.w3.org/ns/csvw", "url": Path(path).name, "dc:title": title,
           "dc:description": f"Numbers carry {int(digits)} significant digits. An empty cell is a value that is "
                             f"unknown or not measured (e.g. the whole size of a bubble cut by the field of view).",
           "dialect": {"header": True}, "null": "", "tableSchema": {"columns": cols}}
    return json.dumps(doc, indent=2) + "\n"


def _checked_columns(rows, columns):
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
    return rows, columns


def write_table(path, rows, columns, *, title, digits=SIGNIFICANT_DIGITS):
    """Write a bubsub table: ``NAME.csv`` and its sidecar ``NAME.csv-metadata.json``, atomically.

    The one way bubsub writes a table (see the module docstring): floats with
    ``digits`` significant digits, unknowns (None, NaN) as empty cells, and the
    CSV-on-the-Web sidecar giving each column's unit, meaning and datatype.

    Parameters
    ----------
    path : str or os.PathLike
        ``NAME.csv``.
    rows : sequence of dict
        One per row, each with exactly the keys of ``columns``.
    columns : dict
        ``{column: (unit, meaning)}`` in column order; the unit is one of
        :data:`UNIT_SUFFIXES` (``""`` or ``"1"`` for ids, counts and other
        dimensionless columns) or a compound such as ``"mm^3/s"``.
    title : str
        Title of the table in the sidecar.
    digits : int
        Significant digits of the floats.

    Returns
    -------
    list of pathlib.Path
        ``[NAME.csv, NAME.csv-metadata.json]`` (for an output folder's manifest).

    Raises
    ------
    ValueError
        If a row's keys differ from the columns; nothing is written then.
    """
    info = dict(columns)
    path = write_csv(path, rows, list(info), describe=info, title=title, digits=digits)
    return [path, csv_metadata_path(path)]


def write_csv(path, rows, columns=None, *, describe=None, title=None, digits=SIGNIFICANT_DIGITS):
    """Write rows (dicts) as CSV with a header line, atomically, and with ``describe`` its sidecar.

    :func:`write_table` is the form to use: it always writes the sidecar.

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
        metadata: name, unit, description and datatype of each column).
    title : str, optional
        Title of the table in the sidecar.
    digits : int
        Significant digits of the floats (:func:`format_cell`).

    Returns
    -------
    pathlib.Path
    """
    rows, columns = _checked_columns(rows, columns)
    # described before anything is written, so an undescribed column writes neither file
    meta = None if describe is None else _csv_metadata(path, columns, describe, title or Path(path).stem, rows,
                                                       digits)
    with atomic_open(path, "w", newline="") as fh:
        if columns:
            w = csv.DictWriter(fh, fieldnames=columns, lineterminator="\n")
            w.writeheader()
            for r in rows:
                w.writerow({k: format_cell(v, digits) for k, v in r.items()})
    if meta is not None:
        with atomic_open(csv_metadata_path(path), "w") as fh:
            fh.write(meta)
    return Path(path)
