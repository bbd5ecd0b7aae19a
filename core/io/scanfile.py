"""HDF5 scan files in the Data Exchange layout.

The writer and the reader (static, dynamic and raw-count files) agree on
every dataset, shape and attribute listed below; the :class:`Scan` they write
and return, and the checks of its fields, are :mod:`bubsub.core.io.scan`
(``Scan`` and ``theta_from_geometry`` are importable from here too, beside the
functions that read and write them).

A scan file holds, for one scan::

    /exchange/data         float32 line integrals, (angle, row, col) in 3D, (angle, col) in 2D
    /exchange/theta        float64 (angle,), degrees (informative; the geometry is authoritative)
    /exchange/background   float32, same shape as data, optional: the projection of
                           everything that is not a bubble (e.g. the liquid container);
                           fitting uses data - background
    /geometry/vectors      float64 (angle, 12) or (angle, 6): ASTRA vector rows,
                           attrs kind (parallel3d_vec | cone_vec | parallel_vec | fanflat_vec),
                           det_rows and det_cols (3D) or det_count (2D), lengths in mm
    /exchange/time         float64 (angle,), seconds, optional: acquisition time of each
                           projection (dynamic scans)
    /implements            "exchange:geometry"
    root attribute bubble_contrast   float, attenuation of gas minus liquid, 1/mm (e.g. -0.1)
    root attribute projections_per_subscan   int, optional: a dynamic scan holds all its
                           projections in acquisition order, this many per subscan (see
                           :mod:`bubsub.core.io.subscans`); a background of one subscan's
                           worth of projections is then repeated for every subscan

Raw detector counts are accepted too: if ``/exchange/data_white`` exists,
``/exchange/data`` is read as raw counts, ``/exchange/data_white`` as flat
fields (``(n_flats, *detector)`` or ``detector`` shaped) and the optional
``/exchange/data_dark`` as dark fields (default 0); both are averaged over
their first axis, and the line integrals are
``-log((data - dark) / (white - dark))``, with the transmission clamped to
at least ``1e-6`` (so a zero count gives about 13.8, not inf): the ``mean``
flat-field correction of ``bubsub prepare`` (:mod:`bubsub.core.flatfield`),
which is its one home.
``/exchange/background`` is always line integrals.

Writes are atomic (temporary file in the same directory, then rename), so a
scan file either exists complete or not at all.
"""

from __future__ import annotations

import numbers
from pathlib import Path

import numpy as np

from bubsub.core.flatfield import mean_flat_model, minus_log
from bubsub.core.io.atomic import atomic_path
from bubsub.core.io.scan import (RESERVED_ATTRS, Scan, check_contrast, check_finite, expected_shape,
                                 per_projection_array, row_slice, row_window_geometry, theta_from_geometry)
from bubsub.core.projection.geometry import KINDS, ScanGeometry

__all__ = ["Scan", "read_scan", "read_geometry", "write_scan", "create_scan_datasets", "set_scan_attrs",
           "theta_from_geometry", "MIN_TRANSMISSION"]

#: Smallest transmission accepted when converting raw counts (larger line integrals are clamped).
MIN_TRANSMISSION = 1e-6


def _attr_value(key, value):
    if isinstance(value, (str, bytes, numbers.Number, np.generic)):
        return value
    arr = np.asarray(value)
    if arr.dtype.kind in "biuf" and arr.ndim <= 1:
        return arr
    raise ValueError(f"attrs[{key!r}] must be a number, string or 1D numeric array, got {type(value).__name__}")


# -- writing -------------------------------------------------------------------------
def write_scan(path, scan, *, compression=None):
    """Write a :class:`Scan` to an HDF5 file (Data Exchange layout), atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Destination; its directory must exist. An existing file is replaced
        only once the new one is complete.
    scan : Scan
    compression : {None, "gzip", "lzf"}
        HDF5 filter for the projection arrays.

    Returns
    -------
    pathlib.Path
        The destination (``scan.path`` is set to it as well).
    """
    import h5py

    if not isinstance(scan, Scan):
        raise ValueError(f"scan must be a Scan, got {type(scan).__name__}")
    if compression not in (None, "gzip", "lzf"):
        raise ValueError(f"compression must be None, 'gzip' or 'lzf', got {compression!r}")
    dest = Path(path)
    with atomic_path(dest) as tmp:
        with h5py.File(tmp, "w") as f:
            data, background = create_scan_datasets(
                f, scan.geometry, scan.theta, background=scan.background is not None, compression=compression
            )
            data[...] = scan.data
            if scan.time is not None:
                f["exchange"].create_dataset("time", data=np.asarray(scan.time, dtype=np.float64)).attrs["units"] = "s"
            if background is not None:
                background[...] = scan.background
            set_scan_attrs(f, scan.bubble_contrast, scan.attrs)
            if scan.projections_per_subscan is not None:
                f.attrs["projections_per_subscan"] = int(scan.projections_per_subscan)
    scan.path = dest
    return dest


def create_scan_datasets(f, geometry, theta, *, background=False, compression=None, chunks=None):
    """Lay out an open, empty HDF5 file as a scan file and return its projection datasets to fill.

    For writers that stream the projections in slabs (``bubsub prepare``);
    :func:`write_scan` uses it too, so both write the same layout. Finish
    with :func:`set_scan_attrs`.

    Parameters
    ----------
    f : h5py.File
        Opened for writing (normally a temporary file of :func:`atomic_path`).
    geometry : ScanGeometry
    theta : (n_angles,) float
        Degrees.
    background : bool
        Create ``/exchange/background`` too.
    compression : {None, "gzip", "lzf"}
    chunks : tuple, optional
        HDF5 chunk shape of the projection datasets.

    Returns
    -------
    data, background : h5py.Dataset, h5py.Dataset or None
        float32, ``geometry.shape``.
    """
    if not isinstance(geometry, ScanGeometry):
        raise ValueError(f"geometry must be a ScanGeometry, got {type(geometry).__name__}")
    g = geometry
    theta = per_projection_array(theta, "theta", g.n_angles)
    f.create_dataset("implements", data="exchange:geometry")
    ex = f.create_group("exchange")
    d = ex.create_dataset("data", shape=g.shape, dtype=np.float32, compression=compression, chunks=chunks)
    d.attrs["axes"] = "theta:y:x" if g.ndim == 3 else "theta:x"
    d.attrs["units"] = "line integral"
    t = ex.create_dataset("theta", data=theta)
    t.attrs["units"] = "degrees"
    b = None
    if background:
        b = ex.create_dataset("background", shape=g.shape, dtype=np.float32, compression=compression, chunks=chunks)
        b.attrs["axes"] = d.attrs["axes"]
        b.attrs["units"] = "line integral"
    geo = f.create_group("geometry")
    v = geo.create_dataset("vectors", data=np.asarray(g.vectors, dtype=np.float64))
    v.attrs["kind"] = g.kind
    v.attrs["units"] = "mm"
    if g.ndim == 3:
        v.attrs["det_rows"] = int(g.det_rows)
        v.attrs["det_cols"] = int(g.det_cols)
    else:
        v.attrs["det_count"] = int(g.det_count)
    return d, b


def set_scan_attrs(f, bubble_contrast, attrs=None):
    """Write the root attributes of a scan file (``bubble_contrast`` in 1/mm, format version, extras)."""
    contrast = check_contrast(bubble_contrast, "bubble_contrast")
    attrs = dict(attrs or {})
    bad = RESERVED_ATTRS.intersection(attrs)
    if bad:
        raise ValueError(f"attrs may not use the reserved names {sorted(bad)}")
    values = {k: _attr_value(k, v) for k, v in attrs.items()}
    f.attrs["bubble_contrast"] = contrast
    f.attrs["bubsub_format"] = 1
    for k, val in values.items():
        f.attrs[k] = val


# -- reading -------------------------------------------------------------------------
def read_scan(path, *, bubble_contrast=None, rows=None):
    """Read and validate a scan file.

    Parameters
    ----------
    path : str or os.PathLike
    bubble_contrast : float, optional
        Overrides (or supplies, if the file lacks it) the root attribute
        ``bubble_contrast``.
    rows : (start, stop) int, optional
        3D scans only: read detector rows ``start:stop`` and nothing else
        (HDF5 hyperslabs of the projections, flats, darks and background), so
        that a slab of a large scan never holds the whole file in memory. The
        geometry is :meth:`ScanGeometry.window` of those rows: the same rays,
        in the same world coordinates (:meth:`Scan.row_window` cuts a scan
        in memory alike).

    Returns
    -------
    Scan
        ``data`` as line integrals (raw counts are converted, see the module
        docstring), ``path`` set.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        If the file is not HDF5, a required dataset or attribute is missing
        (naming it), shapes of data, background, theta and geometry disagree
        (``n_angles``, rows, cols), values are NaN/inf, raw counts are
        negative, the flat field does not exceed the dark field, or the
        geometry kind is unknown.
    """
    import h5py

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"scan file {str(p)!r} does not exist")
    if p.is_dir():
        raise ValueError(f"scan file {str(p)!r} is a directory")
    try:
        f = h5py.File(p, "r")
    except OSError as exc:
        raise ValueError(f"{str(p)!r} is not a readable HDF5 file ({exc}); give a scan file written by bubsub "
                         f"simulate or bubsub prepare") from None
    with f:
        geometry = _read_geometry(f, p)
        full = geometry
        if rows is not None:
            geometry = row_window_geometry(geometry, rows, p.name)
        if "exchange/data" not in f or not isinstance(f["exchange/data"], h5py.Dataset):
            raise ValueError(f"{p.name}: missing dataset '/exchange/data' (the projections)")
        raw = "exchange/data_white" in f
        data = _read_dataset(f, "exchange/data", full, p, rows)
        if raw:
            data = _counts_to_line_integrals(f, data, full, p, rows)
        else:
            _check_finite_named(data, "/exchange/data", p)
        per_subscan = _attr_int(f.attrs, "projections_per_subscan", f"{p.name}: root")
        background = None
        if "exchange/background" in f:
            background = _read_background(f, full, per_subscan, p, rows)
        theta = _read_per_projection(f, "exchange/theta", geometry, p)
        time_s = _read_per_projection(f, "exchange/time", geometry, p)
        if bubble_contrast is None:
            if "bubble_contrast" not in f.attrs:
                raise ValueError(
                    f"{p.name}: missing root attribute 'bubble_contrast' (gas minus liquid attenuation, "
                    f"1/mm); add it to the file or pass bubble_contrast="
                )
            bubble_contrast = f.attrs["bubble_contrast"]
        try:
            bubble_contrast = check_contrast(np.asarray(bubble_contrast).item(), "bubble_contrast")
        except ValueError as exc:
            raise ValueError(f"{p.name}: {exc}") from None
        attrs = {}
        for k, v in f.attrs.items():
            if k in RESERVED_ATTRS:
                continue
            attrs[k] = v.decode() if isinstance(v, bytes) else (v.item() if isinstance(v, np.generic) else v)
    return Scan(
        data=data,
        geometry=geometry,
        theta=theta,
        background=background,
        bubble_contrast=bubble_contrast,
        path=p,
        attrs=attrs,
        time=time_s,
        projections_per_subscan=per_subscan,
    )


def read_geometry(path):
    """The :class:`ScanGeometry` of a scan file, read without its projections.

    Raises
    ------
    FileNotFoundError, ValueError
        As :func:`read_scan` for the file and its ``/geometry/vectors``.
    """
    import h5py

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"scan file {str(p)!r} does not exist")
    try:
        f = h5py.File(p, "r")
    except OSError as exc:
        raise ValueError(f"{str(p)!r} is not a readable HDF5 file ({exc}); give a scan file written by bubsub "
                         f"simulate or bubsub prepare") from None
    with f:
        return _read_geometry(f, p)


def _read_per_projection(f, name, geometry, p):
    """A per-projection 1D dataset (theta, time) or None; its length must match the geometry rows."""
    if name not in f:
        return None
    arr = np.asarray(f[name][()], dtype=np.float64)
    if arr.ndim != 1 or arr.shape[0] != geometry.n_angles:
        raise ValueError(
            f"{p.name}: '/{name}' has shape {arr.shape} but '/geometry/vectors' has {geometry.n_angles} projections"
        )
    _check_finite_named(arr, "/" + name, p)
    return arr


def _read_background(f, geometry, per_subscan, p, rows=None):
    """``/exchange/background``, per projection or (dynamic scans) one subscan's worth repeated."""
    ds = f["exchange/background"]
    if per_subscan is not None and ds.shape == (per_subscan, *geometry.shape[1:]) and ds.shape != geometry.shape:
        one = np.asarray(ds[(slice(None), row_slice(rows)) if rows is not None else ()])
        _check_finite_named(one, "/exchange/background", p)
        reps = -(-geometry.n_angles // per_subscan)
        return np.tile(one, (reps,) + (1,) * (one.ndim - 1))[: geometry.n_angles]
    background = _read_dataset(f, "exchange/background", geometry, p, rows)
    _check_finite_named(background, "/exchange/background", p)
    return background


def _attr_str(v):
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.ndarray) and v.shape == ():
        v = v.item()
        return v.decode() if isinstance(v, bytes) else str(v)
    return v if isinstance(v, str) else str(v)


def _attr_int(attrs, key, where):
    if key not in attrs:
        return None
    v = attrs[key]
    try:
        arr = np.asarray(v)
        if arr.size != 1 or not (np.issubdtype(arr.dtype, np.integer) or (
            np.issubdtype(arr.dtype, np.floating) and float(arr) == int(arr)
        )):
            raise TypeError
        n = int(arr.reshape(()))
    except (TypeError, ValueError):
        raise ValueError(f"{where}: attribute '{key}' must be a positive integer, got {v!r}") from None
    if n < 1:
        raise ValueError(f"{where}: attribute '{key}' must be a positive integer, got {n}")
    return n


def _read_geometry(f, p):
    import h5py

    if "geometry/vectors" not in f or not isinstance(f["geometry/vectors"], h5py.Dataset):
        raise ValueError(f"{p.name}: missing dataset '/geometry/vectors' (the ASTRA vector geometry)")
    ds = f["geometry/vectors"]
    where = f"{p.name}: '/geometry/vectors'"
    if "kind" not in ds.attrs:
        raise ValueError(f"{where} has no attribute 'kind' (one of {sorted(KINDS)})")
    kind = _attr_str(ds.attrs["kind"])
    if kind not in KINDS:
        raise ValueError(f"{where} has kind {kind!r}; expected one of {sorted(KINDS)}")
    ndim, width, _ = KINDS[kind]
    vectors = np.asarray(ds[()])
    if vectors.ndim != 2 or vectors.shape[1] != width or vectors.shape[0] == 0:
        raise ValueError(f"{where} has shape {vectors.shape}; kind {kind} needs (n_angles, {width})")
    if not np.issubdtype(vectors.dtype, np.number):
        raise ValueError(f"{where} must be numeric, got dtype {vectors.dtype}")
    _check_finite_named(vectors.astype(np.float64), "/geometry/vectors", p)
    if ndim == 3:
        rows = _attr_int(ds.attrs, "det_rows", where)
        cols = _attr_int(ds.attrs, "det_cols", where)
        if rows is None or cols is None:
            missing = [k for k, v in (("det_rows", rows), ("det_cols", cols)) if v is None]
            raise ValueError(f"{where} (kind {kind}) is missing attribute(s) {missing}")
        kw = dict(det_rows=rows, det_cols=cols)
    else:
        count = _attr_int(ds.attrs, "det_count", where)
        if count is None:
            count = _attr_int(ds.attrs, "det_cols", where)
        if count is None:
            raise ValueError(f"{where} (kind {kind}) is missing attribute 'det_count'")
        kw = dict(det_count=count)
    try:
        return ScanGeometry.from_astra(kind, vectors, **kw)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


def _read_dataset(f, name, geometry, p, rows=None):
    """Dataset ``name`` of the geometry's shape (checked), or its detector rows ``rows`` only (a hyperslab)."""
    ds = f[name]
    if ds.shape != geometry.shape:
        raise ValueError(
            f"{p.name}: '/{name}' has shape {ds.shape} but '/geometry/vectors' describes "
            f"{expected_shape(geometry, ds.shape)}"
        )
    if not (np.issubdtype(ds.dtype, np.floating) or np.issubdtype(ds.dtype, np.integer)):
        raise ValueError(f"{p.name}: '/{name}' must be numeric, got dtype {ds.dtype}")
    return np.asarray(ds[()] if rows is None else ds[:, row_slice(rows)])


def _check_finite_named(arr, name, p):
    """:func:`check_finite` of dataset ``name`` of file ``p``."""
    check_finite(arr, f"{p.name}: '{name}'")


def _read_field(f, name, det_shape, p, rows=None):
    """A flat or dark field averaged to the detector shape (float64), or to its rows ``rows``."""
    ds = f[name]
    if rows is not None and ds.ndim in (len(det_shape), len(det_shape) + 1) and ds.shape[-2:] == tuple(det_shape):
        cut = (row_slice(rows),) if ds.ndim == len(det_shape) else (slice(None), row_slice(rows))
        arr = np.asarray(ds[cut], dtype=np.float64)
        det_shape = (int(rows[1]) - int(rows[0]), *det_shape[1:])
    else:
        arr = np.asarray(ds[()], dtype=np.float64)
    if arr.shape == det_shape:
        field = arr
    elif arr.ndim == len(det_shape) + 1 and arr.shape[1:] == det_shape and arr.shape[0] >= 1:
        field = None
    else:
        raise ValueError(
            f"{p.name}: '/{name}' has shape {arr.shape}; expected {det_shape} or (n, *{det_shape}) "
            f"to match the detector of '/exchange/data'"
        )
    _check_finite_named(arr, "/" + name, p)
    if np.any(arr < 0):
        raise ValueError(f"{p.name}: '/{name}' has {int((arr < 0).sum())} negative counts")
    return arr.mean(axis=0) if field is None else field


def _counts_to_line_integrals(f, counts, geometry, p, rows=None):
    counts = counts.astype(np.float64)
    _check_finite_named(counts, "/exchange/data", p)
    if np.any(counts < 0):
        raise ValueError(
            f"{p.name}: '/exchange/data' holds raw counts (because '/exchange/data_white' exists) "
            f"but has {int((counts < 0).sum())} negative values"
        )
    det = geometry.shape[1:]
    white = _read_field(f, "exchange/data_white", det, p, rows)
    if rows is not None:
        det = white.shape
    dark = _read_field(f, "exchange/data_dark", geometry.shape[1:], p, rows) if "exchange/data_dark" in f \
        else np.zeros(det)
    span = white - dark
    if np.any(span <= 0):
        raise ValueError(
            f"{p.name}: '/exchange/data_white' must exceed '/exchange/data_dark' at every detector pixel "
            f"({int((span <= 0).sum())} pixels do not)"
        )
    trans, _ = mean_flat_model(white, dark).transmission(counts, None)
    return minus_log(trans, MIN_TRANSMISSION).astype(np.float32, copy=False)
