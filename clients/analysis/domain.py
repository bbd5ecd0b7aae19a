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
3. the sample the scan's background shows (:func:`background_sample`): the
   box or the cylinder about the rotation axis whose chords, times an
   attenuation, fit the background best, when the fit is within
   :data:`TRUSTED_FIT`;
4. the field of view (report.json's ``field_of_view_mm``), when the sample is
   not known;
5. the bubbles' bounding box, when neither is.

The sample is cut to the field of view (what the scan reconstructs). The
summary's ``domain`` says which was used: ``kind``, bounds, ``radius_mm``
and ``source``.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
from scipy.optimize import least_squares

from bubsub.core.analysis.regions import Domain
from bubsub.core.io.scanfile import read_geometry

__all__ = ["parse_domain", "simulated_sample", "background_sample", "analysed_domain", "DOMAIN_FORMS"]

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


#: Views and detector pixels per axis of the background that :func:`background_sample` fits.
BACKGROUND_VIEWS, BACKGROUND_PIXELS = 12, 32
#: A box fitting the background this well (relative residual) is taken without trying the cylinder.
GOOD_FIT = 0.01
#: A sample fitted to the background worse than this (relative residual) is not taken for the sample.
TRUSTED_FIT = 0.2


def _rays(geometry, step_rows, step_cols):
    """Origins and unit directions of the rays through every ``step``-th pixel of each view: (k, 3) each."""
    vec = geometry.vectors
    s, d, u, v = vec[:, 0:3], vec[:, 3:6], vec[:, 6:9], vec[:, 9:12]
    rows = np.arange(0, geometry.det_rows, step_rows)
    cols = np.arange(0, geometry.det_cols, step_cols)
    r = (rows - geometry.det_rows / 2 + 0.5)[None, :, None, None]
    c = (cols - geometry.det_cols / 2 + 0.5)[None, None, :, None]
    pixel = d[:, None, None] + c * u[:, None, None] + r * v[:, None, None]
    if geometry.is_cone:
        origin = np.broadcast_to(s[:, None, None], pixel.shape)
        direction = pixel - origin
    else:
        direction = np.broadcast_to(s[:, None, None], pixel.shape)
        origin = pixel - 1e3 * direction / np.linalg.norm(direction, axis=-1, keepdims=True)
    direction = direction / np.linalg.norm(direction, axis=-1, keepdims=True)
    return origin.reshape(-1, 3), direction.reshape(-1, 3), rows, cols


def _box_chords(origin, direction, p):
    """Lengths of the rays inside the box ``p = (x0, x1, y0, y1, z0, z1)``."""
    lo, hi = np.asarray(p[0::2]), np.asarray(p[1::2])
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - origin) / direction, (hi - origin) / direction
    near = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2)).max(axis=1)
    far = np.where(np.isnan(t2), np.inf, np.maximum(t1, t2)).min(axis=1)
    return np.maximum(far - near, 0.0)


def _cylinder_chords(origin, direction, p):
    """Lengths of the rays inside the cylinder ``p = (radius, z0, z1)`` about the z axis."""
    radius, z0, z1 = p
    ox, oy = origin[:, 0], origin[:, 1]
    a = direction[:, 0] ** 2 + direction[:, 1] ** 2
    b = ox * direction[:, 0] + oy * direction[:, 1]
    disc = b * b - a * (ox * ox + oy * oy - radius * radius)
    root = np.sqrt(np.maximum(disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        near_r, far_r = (-b - root) / a, (-b + root) / a
        tz1, tz2 = (z0 - origin[:, 2]) / direction[:, 2], (z1 - origin[:, 2]) / direction[:, 2]
    near = np.maximum(near_r, np.where(np.isnan(tz1), -np.inf, np.minimum(tz1, tz2)))
    far = np.minimum(far_r, np.where(np.isnan(tz2), np.inf, np.maximum(tz1, tz2)))
    return np.where((disc > 0) & (a > 0), np.maximum(far - near, 0.0), 0.0)


def _fit(model, start, origin, direction, values):
    """Least-squares fit of ``attenuation x chord`` to the background; ``(params, relative residual)``."""
    def residual(p):
        chord = model(origin, direction, p)
        mu = float(chord @ values) / max(float(chord @ chord), 1e-30)
        return mu * chord - values

    fit = least_squares(residual, start, diff_step=1e-4, x_scale="jac", xtol=1e-6)
    return fit.x, float(np.linalg.norm(fit.fun) / max(np.linalg.norm(values), 1e-30))


def background_sample(scan_path):
    """The sample a 3D scan's background shows: a box or a cylinder about a z-parallel axis, fitted.

    The background is the projection of everything but the bubbles: for a
    sample of uniform liquid, its attenuation times each ray's chord through
    the sample. Both models (box ``x0..z1``; cylinder ``cx, cy, radius,
    z0..z1``) are fitted by least squares to :data:`BACKGROUND_VIEWS` views of
    it on :data:`BACKGROUND_PIXELS` pixels per detector axis (the
    attenuation solved for at each step), from the bounding box of the pixels
    it covers; the better fit is the sample (a box within :data:`GOOD_FIT` is
    taken at once). A cylinder is about the rotation axis, the z axis.

    Parameters
    ----------
    scan_path : str or os.PathLike
        A scan file with ``/exchange/background``.

    Returns
    -------
    domain : Domain or None
        None for a 2D scan, one without a background or with a background of nothing.
    residual : float or None
        The fit's relative residual ``|mu L - background| / |background|``.
    """

    g = read_geometry(scan_path)
    if g.ndim != 3:
        return None, None
    with h5py.File(scan_path, "r") as f:
        if "exchange/background" not in f:
            return None, None
        ds = f["exchange/background"]
        n = min(int(ds.shape[0]), g.n_angles)
        views = np.unique(np.linspace(0, n - 1, min(BACKGROUND_VIEWS, n)).round().astype(int))
        sr, sc = max(1, -(-g.det_rows // BACKGROUND_PIXELS)), max(1, -(-g.det_cols // BACKGROUND_PIXELS))
        values = np.stack([np.asarray(ds[int(i), ::sr, ::sc], dtype=float) for i in views]).reshape(-1)
    if not np.all(np.isfinite(values)) or not values.max() > 0:
        return None, None
    origin, direction, _, _ = _rays(g[views], sr, sc)
    # a start that holds the sample: the box of the points every covering ray passes nearest the axis
    covered = values > 0.05 * values.max()
    t = -np.einsum("ij,ij->i", origin[covered, :2], direction[covered, :2]) / np.maximum(
        np.einsum("ij,ij->i", direction[covered, :2], direction[covered, :2]), 1e-12)
    near = origin[covered] + t[:, None] * direction[covered]
    r0 = float(np.percentile(np.hypot(near[:, 0], near[:, 1]), 99))
    z0, z1 = float(near[:, 2].min()), float(near[:, 2].max())
    box, box_res = _fit(_box_chords, [-r0, r0, -r0, r0, z0, z1], origin, direction, values)
    if box_res < GOOD_FIT:
        return Domain.box(box), box_res
    cyl, cyl_res = _fit(_cylinder_chords, [r0, z0, z1], origin, direction, values)
    if box_res <= cyl_res:
        return Domain.box(box), box_res
    return Domain.cylinder(abs(cyl[0]), min(cyl[1], cyl[2]), max(cyl[1], cyl[2])), cyl_res


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
        scan = _scan_path(report, folder)
        if domain is None and scan is not None:
            try:
                domain, residual = background_sample(scan)
            except (OSError, ValueError, KeyError):  # a scan file that cannot say: the field of view, as without one
                domain, residual = None, None
            if domain is not None and residual > TRUSTED_FIT:
                domain = None
            source = None if domain is None else (f"the sample fitted to the scan's background ({scan}, relative "
                                                  f"residual {residual:.2g})")
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
