"""The analysed domain of ``bubsub analyse``: the sample within the field of view.

Liquid fractions count everything outside the bubbles as liquid, so the
domain must be the sample (the liquid box of a simulated foam, the column of
a real one), not the field of view around it. :func:`analysed_domain` takes,
in this order,

1. the domain asked for (``--domain``, :func:`parse_domain`):
   ``box:X0,X1,Y0,Y1,Z0,Z1``, ``cylinder:R`` (over the field of view's height),
   ``cylinder:R,Z0,Z1`` (about the rotation axis, the z axis), ``fov`` (the
   field of view) or ``sample`` (the default: what follows);
2. the sample the scan's simulation describes: ``phantom.json`` beside the
   scan that report.json names (``bubsub simulate`` writes it): the liquid
   box of ``size`` centred at the origin, or the ``column`` phantom's
   cylinder;
3. the field of view (report.json's ``field_of_view_mm``), when the sample is
   not known;
4. the bubbles' bounding box, when neither is.

The sample is cut to the field of view (what the scan reconstructs). The
summary's ``domain`` says which was used: ``kind``, bounds, ``radius_mm``
and ``source``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bubsub.core.analysis.regions import Domain

__all__ = ["parse_domain", "simulated_sample", "analysed_domain", "DOMAIN_FORMS"]

#: The forms ``--domain`` takes, for messages and help.
DOMAIN_FORMS = "sample, fov, box:X0,X1,Y0,Y1,Z0,Z1 or cylinder:R[,Z0,Z1] (mm)"


def parse_domain(text, field_of_view=None):
    """A ``--domain`` value as a :class:`~bubsub.core.analysis.regions.Domain`, or ``"sample"`` / ``"fov"``.

    Parameters
    ----------
    text : str
        One of :data:`DOMAIN_FORMS`.
    field_of_view : (radius, half_height), optional
        mm; gives ``cylinder:R`` its height.

    Returns
    -------
    Domain or str

    Raises
    ------
    ValueError
        One line naming the forms, for anything else.
    """
    t = str(text).strip().lower()
    if t in ("sample", "fov"):
        return t
    kind, _, rest = t.partition(":")
    try:
        values = [float(v) for v in rest.split(",")] if rest else []
    except ValueError:
        values = None
    if values is not None and kind == "box" and len(values) == 6:
        return Domain.box(values)
    if values is not None and kind == "cylinder" and len(values) in (1, 3):
        if len(values) == 3:
            return Domain.cylinder(*values)
        if field_of_view is None:
            raise ValueError(f"--domain {text}: the report gives no field of view for the cylinder's height; give "
                             f"it as cylinder:R,Z0,Z1")
        return Domain.cylinder(values[0], -field_of_view[1], field_of_view[1])
    raise ValueError(f"--domain {text!r} is not one of {DOMAIN_FORMS}")


def _scan_path(report, folder):
    scan = report.get("scan")
    if not scan:
        return None
    p = Path(scan)
    for candidate in ([p] if p.is_absolute() else [Path.cwd() / p, Path(folder) / p, Path(folder).parent / p]):
        if candidate.is_file():
            return candidate
    return None


def simulated_sample(report, folder):
    """The sample of the simulation the reconstruction's scan comes from (``phantom.json`` beside it).

    Parameters
    ----------
    report : dict
        The reconstruction's report.json (its ``scan``).
    folder : str or os.PathLike
        The reconstruction's folder (a relative ``scan`` is looked for from the current folder and from it).

    Returns
    -------
    domain : Domain or None
        The liquid box (``size`` centred at the origin) or the column's cylinder; None when the scan or
        its ``phantom.json`` is not found or describes no 3D sample.
    source : str or None
        The ``phantom.json`` read.
    """
    scan = _scan_path(report, folder)
    meta_path = None if scan is None else scan.parent / "phantom.json"
    if meta_path is None or not meta_path.is_file():
        return None, None
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, ValueError):
        return None, None
    if not isinstance(meta, dict) or meta.get("ndim") != 3:
        return None, None
    column = meta.get("column")
    if isinstance(column, dict) and column.get("radius_mm") and column.get("z_range_mm"):
        return Domain.cylinder(column["radius_mm"], *column["z_range_mm"]), str(meta_path)
    size = meta.get("size")
    if not (isinstance(size, list) and len(size) == 3):
        return None, None
    half = np.asarray(size, dtype=float) / 2.0
    return Domain.box([v for h in half for v in (-h, h)]), str(meta_path)


def analysed_domain(spec, report, folder, field_of_view):
    """The analysed domain and where it comes from (see the module docstring).

    Parameters
    ----------
    spec : str, Domain or None
        ``--domain`` (None: ``"sample"``).
    report : dict
        The reconstruction's report.json.
    folder : str or os.PathLike
        The reconstruction's folder.
    field_of_view : (radius, half_height) or None
        mm.

    Returns
    -------
    domain : Domain or None
        None: the bubbles' bounding box (neither the sample nor the field of view is known).
    source : str
    """
    spec = parse_domain(spec, field_of_view) if isinstance(spec, str) else (spec or "sample")
    fov = None if field_of_view is None else Domain.field_of_view(*field_of_view)
    if isinstance(spec, Domain):
        domain, source = spec, "asked for (--domain)"
    elif spec == "sample":
        domain, source = simulated_sample(report, folder)
        source = None if source is None else f"the simulated sample ({source})"
    else:
        domain, source = None, None
    if domain is None:
        if fov is None:
            return None, "the bounding box of the bubbles (neither the sample nor the field of view is known)"
        what = "asked for (--domain fov)" if spec == "fov" else "the sample is not known: pass --domain"
        return fov, f"the field of view ({what})"
    if fov is not None:
        domain = domain.intersect(fov)
        source += ", within the field of view"
    return domain, source
