"""Column names, units and meanings of the 4D analysis tables (their time unit is the scan's).

:func:`dynamics_columns` maps the keys the functions of
:mod:`bubsub.core.analysis.dynamics` return to the CSV columns (names ending
with their unit, as every bubsub table) and :func:`named_rows` renames rows.
"""

from __future__ import annotations

__all__ = ["dynamics_columns", "named_rows", "describe"]


def dynamics_columns(time_unit):
    """``{table: {key: (column, unit, meaning)}}`` of the 4D tables.

    Parameters
    ----------
    time_unit : {"s", "subscan"}
        Seconds, or the subscan index where the scan has no times.

    Returns
    -------
    dict
        Tables ``rates``, ``t1``, ``events``, ``sizes``, ``distribution``.
    """
    if time_unit not in ("s", "subscan"):
        raise ValueError(f"time_unit must be 's' or 'subscan', got {time_unit!r}")
    t = f"time_{time_unit}"
    per = f"per_{time_unit}"
    when = "mid-time of the subscan" if time_unit == "s" else "subscan index (the scan has no times)"
    step = {"subscan": ("subscan", "", "subscan index"), "time": (t, time_unit, when)}
    between = {
        "subscan_before": ("subscan_before", "", "subscan before the change"),
        "subscan_after": ("subscan_after", "", "subscan after the change"),
        "time_before": (f"{t}_before", time_unit, f"{when}, before"),
        "time_after": (f"{t}_after", time_unit, f"{when}, after"),
    }
    where = {a: (f"{a}_mm", "mm", f"{a} coordinate of the event") for a in "xyz"}
    return {
        "rates": {
            **step,
            "bubble_id": ("bubble_id", "", "track id"),
            "volume": ("volume_mm3", "mm^3", "volume at this subscan"),
            "coordination": ("coordination", "1", "contacts at this subscan"),
            "volume_rate": (f"volume_rate_mm3_{per}", f"mm^3/{time_unit}",
                            "dV/dt, central difference over the neighbouring subscans (one-sided at a track's end)"),
            "two_thirds_rate": (f"volume_two_thirds_rate_mm2_{per}", f"mm^2/{time_unit}",
                                "d(V^(2/3))/dt, the growth law's rate, by the same differences"),
        },
        "t1": {
            **between,
            "lost_a": ("lost_a", "", "bubble of the contact lost"),
            "lost_b": ("lost_b", "", "other bubble of the contact lost"),
            "gained_c": ("gained_c", "", "bubble of the contact gained"),
            "gained_d": ("gained_d", "", "other bubble of the contact gained"),
            **{a: (f"{a}_mm", "mm", f"{a} of the mean centroid of the four bubbles over both subscans")
               for a in "xyz"},
        },
        "events": {
            **between,
            "kind": ("kind", "", "coalescence, disappearance or appearance"),
            "bubble_id": ("bubble_id", "", "the bubble that disappeared or appeared"),
            "partner_id": ("partner_id", "", "coalescence: the bubble it merged into (lineage.csv's merged track "
                                             "where the reconstruction recorded it, else the neighbour that gained "
                                             "most volume)"),
            "volume": ("volume_mm3", "mm^3", "its volume where it exists (empty when cut by the field of view)"),
            **where,
        },
        "sizes": {
            **step,
            "bubbles": ("bubbles", "1", "bubbles at this subscan"),
            "bubbles_whole": ("bubbles_whole", "1", "of them not cut by the field of view (the statistics' sample)"),
            "mean_radius": ("mean_radius_mm", "mm", "mean equivalent radius"),
            "median_radius": ("median_radius_mm", "mm", "median equivalent radius"),
            "std_radius": ("std_radius_mm", "mm", "standard deviation of the equivalent radii"),
            "sauter_radius": ("sauter_radius_mm", "mm", "Sauter mean radius, sum r^3 / sum r^2"),
            "gas_volume": ("gas_volume_mm3", "mm^3", "total volume of the whole bubbles"),
        },
        "distribution": {
            **step,
            "r_lo": ("radius_lo_mm", "mm", "lower edge of the equivalent-radius bin"),
            "r_hi": ("radius_hi_mm", "mm", "upper edge of the bin"),
            "bubbles": ("bubbles", "1", "whole bubbles in the bin"),
            "fraction": ("fraction", "1", "their fraction of the subscan's whole bubbles"),
        },
    }


def _cell(v):
    if v is None:
        return ""
    if isinstance(v, float) and v != v:  # NaN: an empty cell, as bubsub's tables leave unknowns
        return ""
    return v


def named_rows(rows, spec):
    """Rows renamed to their CSV columns, unknowns (None, NaN) as empty cells.

    Parameters
    ----------
    rows : list of dict
        With the keys of ``spec``.
    spec : dict
        ``{key: (column, unit, meaning)}`` (a table of :func:`dynamics_columns`).

    Returns
    -------
    list of dict
    """
    return [{spec[k][0]: _cell(r[k]) for k in spec} for r in rows]


def describe(spec):
    """``{column: (unit, meaning)}`` of a spec, for :func:`bubsub.core.io.tables.write_csv`."""
    return {c: (u, m) for c, u, m in spec.values()}
