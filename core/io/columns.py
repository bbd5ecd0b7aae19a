"""Column names that carry their units, and the columns of the bubble tables with their units and meanings.

Kept apart from :mod:`bubsub.core.io.tables` (which writes the tables, measuring 3D bubbles with
:func:`bubsub.core.analysis.shape.bubble_sizes`) so that the analysis can describe its columns in the same
words without importing the writer.
"""

from __future__ import annotations

__all__ = ["UNIT_SUFFIXES", "unit_column", "BUBBLE_COLUMN_INFO", "FOV_COLUMN_INFO"]

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


#: ``column name: (unit, meaning)`` of every column :func:`bubsub.core.analysis.shape.bubble_table` writes;
#: ``bubsub analyse``'s ``bubbles.csv`` describes the same columns with the same words
#: (:data:`bubsub.core.analysis.shape.SHAPE_COLUMN_INFO`).
BUBBLE_COLUMN_INFO = {
    "id": ("", "bubble id (the bubble_id of the PLY faces / the id of the JSON polygon)"),
    **{unit_column(f"centroid_{a}", "mm"): ("mm", f"{a} coordinate of the centroid of the area (2D) or solid (3D) "
                                                  f"the refined outline or surface encloses") for a in "xyz"},
    unit_column("area", "mm^2"): ("mm^2", "area enclosed by the refined 2D outline"),
    unit_column("perimeter", "mm"): ("mm", "length of the refined 2D outline"),
    unit_column("volume", "mm^3"): ("mm^3", "volume enclosed by the refined 3D surface"),
    unit_column("surface_area", "mm^2"): (
        "mm^2", "area of the smooth (Loop limit) surface of the refined 3D surface, scaled to the refined surface's "
                "volume (bubsub.core.analysis.shape.bubble_sizes)"),
    unit_column("equivalent_diameter", "mm"): (
        "mm", "diameter of the disc (2D) or ball (3D) of the same area (volume): 2 sqrt(A / pi), (6 V / pi)^(1/3)"),
}

#: ``column name: (unit, meaning)`` of the field-of-view columns of ``bubbles.csv`` (and ``tracks.csv``), which
#: ``bubsub.clients.pipeline.inputs.fov.fov_columns`` adds and ``bubsub analyse`` carries over.
FOV_COLUMN_INFO = {
    "truncated": ("1", "1 if the bubble reaches the edge of the field of view (the disc every projection sees, or "
                       "the detector's top or bottom): its whole-size and shape columns are empty (not measured) and "
                       "bubsub analyse leaves it out of its statistics; 0 otherwise; empty where the field of view is "
                       "unknown"),
    unit_column("area_in_fov", "mm^2"): (
        "mm^2", "area of the part of the refined outline inside the field of view (the measured part; equals "
                "area_mm2 when truncated is 0)"),
    unit_column("volume_in_fov", "mm^3"): (
        "mm^3", "volume of the part of the refined surface inside the field of view (the measured part; equals "
                "volume_mm3 when truncated is 0; empty where the field of view is unknown)"),
    "unobserved_control_vertices": ("1", "control vertices whose refined neighbourhood no ray of the data sees "
                                         "(held at their initial position by the fit, not measured)"),
}
