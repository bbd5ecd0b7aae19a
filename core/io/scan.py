"""A scan in memory: :class:`Scan` (projections, geometry, contrast, optional background, time and
subscans) and the checks its fields pass.

:class:`Scan` checks every field when it is made, so that whatever holds one
(read from a file, simulated, cut to a subset of projections or to detector
rows) holds consistent shapes and finite values. The checks are public for
the scan file's reader and writer (:mod:`bubsub.core.io.scanfile`), which
report the same problems of a file's datasets with the dataset's name.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.validate import check_int

__all__ = ["Scan", "theta_from_geometry", "check_finite", "check_contrast", "projection_array",
           "per_projection_array", "expected_shape", "row_window_geometry", "row_slice", "RESERVED_ATTRS"]

#: Root attributes of a scan file that the :class:`Scan` fields own (``Scan.attrs`` may not use them).
RESERVED_ATTRS = {"bubble_contrast", "bubsub_format", "projections_per_subscan"}


def theta_from_geometry(geometry):
    """Rotation angle of each projection, degrees, from a circular-scan geometry.

    The angle of the ray direction (parallel beams) or of the source
    position (cone/fan beams) in the x-y plane, measured as in
    :meth:`ScanGeometry.parallel` / :meth:`ScanGeometry.cone`
    (``theta = atan2(x, -y)``), unwrapped so that consecutive angles do not
    jump by 360 degrees.

    Parameters
    ----------
    geometry : ScanGeometry

    Returns
    -------
    (n_angles,) float64
        Degrees.
    """
    if not isinstance(geometry, ScanGeometry):
        raise ValueError(f"geometry must be a ScanGeometry, got {type(geometry).__name__}")
    v = geometry.vectors
    th = np.arctan2(v[:, 0], -v[:, 1])
    return np.degrees(np.unwrap(th))


@dataclasses.dataclass(eq=False)
class Scan:
    """One scan: projections, geometry and what the fit needs to know.

    Parameters
    ----------
    data : ndarray, shape ``geometry.shape``
        Line integrals (``-log`` of the flat-field-corrected transmission),
        ``(angle, row, col)`` in 3D or ``(angle, col)`` in 2D; stored float32.
    geometry : ScanGeometry
    theta : (n_angles,) float, optional
        Rotation angles in degrees; derived from the geometry if omitted
        (:func:`theta_from_geometry`).
    background : ndarray, shape ``geometry.shape``, optional
        Projection of everything but the bubbles (e.g. the liquid container),
        float32. :attr:`bubble_data` is ``data - background``.
    bubble_contrast : float
        Attenuation of the gas minus that of the liquid, 1/mm (e.g. -0.1);
        required and non-zero.
    path : pathlib.Path, optional
        File the scan was read from or written to.
    attrs : dict, optional
        Extra scalar or string metadata (written as root attributes), e.g.
        ``photons`` and ``seed`` of a simulation.
    time : (n_angles,) float, optional
        Acquisition time of each projection, seconds (dynamic scans).
    projections_per_subscan : int, optional
        A dynamic scan's projections per subscan (acquisition order).

    Raises
    ------
    ValueError
        If shapes disagree with the geometry, values are not finite, or
        ``bubble_contrast`` is missing or zero.
    """

    data: np.ndarray
    geometry: ScanGeometry
    theta: np.ndarray | None = None
    background: np.ndarray | None = None
    bubble_contrast: float | None = None
    path: Path | None = None
    attrs: dict = dataclasses.field(default_factory=dict)
    time: np.ndarray | None = None
    projections_per_subscan: int | None = None

    def __post_init__(self):
        if not isinstance(self.geometry, ScanGeometry):
            raise ValueError(f"geometry must be a ScanGeometry, got {type(self.geometry).__name__}")
        self.data = projection_array(self.data, "data", self.geometry)
        if self.background is not None:
            self.background = projection_array(self.background, "background", self.geometry)
        if self.theta is None:
            self.theta = theta_from_geometry(self.geometry)
        else:
            self.theta = per_projection_array(self.theta, "theta", self.geometry.n_angles)
        self.bubble_contrast = check_contrast(self.bubble_contrast, "bubble_contrast")
        if self.time is not None:
            self.time = per_projection_array(self.time, "time", self.geometry.n_angles)
        if self.projections_per_subscan is not None:
            k = self.projections_per_subscan
            check_int(k, "projections_per_subscan", 1)
            self.projections_per_subscan = int(k)
        if self.path is not None:
            self.path = Path(self.path)
        if not isinstance(self.attrs, dict):
            raise ValueError(f"attrs must be a dict, got {type(self.attrs).__name__}")
        bad = RESERVED_ATTRS.intersection(self.attrs)
        if bad:
            raise ValueError(f"attrs may not use the reserved names {sorted(bad)}")
        self.attrs = dict(self.attrs)

    @property
    def ndim(self):
        """2 or 3."""
        return self.geometry.ndim

    @property
    def n_angles(self):
        return self.geometry.n_angles

    @property
    def bubble_data(self):
        """``data - background`` (or ``data`` without a background), float32, ``geometry.shape``."""
        if self.background is None:
            return self.data
        return (self.data - self.background).astype(np.float32)

    def subset(self, index):
        """The scan restricted to some projections (``scan.subset(slice(0, None, 2))``).

        Parameters
        ----------
        index : slice, int or array of int
            Projection indices, as for ``geometry[index]``.

        Returns
        -------
        Scan
            With ``path`` None and ``projections_per_subscan`` None (a subset
            is one static scan).
        """
        idx = np.atleast_1d(np.arange(self.n_angles)[index])
        if idx.size == 0:
            raise ValueError("subset selects no projections")
        return Scan(
            data=self.data[idx],
            geometry=self.geometry[idx],
            theta=self.theta[idx],
            background=None if self.background is None else self.background[idx],
            bubble_contrast=self.bubble_contrast,
            path=None,
            attrs=dict(self.attrs),
            time=None if self.time is None else self.time[idx],
        )

    def row_window(self, rows):
        """Detector rows ``rows = (start, stop)`` of a 3D scan: what
        :func:`~bubsub.core.io.scanfile.read_scan` with ``rows=`` reads of the scan's file.

        Parameters
        ----------
        rows : (start, stop) int

        Returns
        -------
        Scan
            The geometry :meth:`ScanGeometry.window` of those rows (the same rays, in the same world
            coordinates), data and background cut to them, every other field kept.

        Raises
        ------
        ValueError
            For a 2D scan, or rows that do not lie within the detector.
        """
        geometry = row_window_geometry(self.geometry, rows, self.path.name if self.path is not None else "the scan")
        cut = (slice(None), row_slice(rows))
        return dataclasses.replace(self, data=self.data[cut], geometry=geometry,
                                   background=None if self.background is None else self.background[cut])

    def __repr__(self):
        bg = "yes" if self.background is not None else "no"
        return (
            f"Scan({self.geometry.kind}, shape={self.data.shape}, background={bg}, "
            f"bubble_contrast={self.bubble_contrast!r}, path={str(self.path) if self.path else None!r})"
        )


def _dynamic_hint(shape, geometry):
    """A hint when ``shape`` looks like several rotations of a geometry given once (a dynamic scan)."""
    if len(shape) == len(geometry.shape) and shape[0] > geometry.n_angles and shape[0] % geometry.n_angles == 0:
        return " (a dynamic scan needs one geometry row per projection, in acquisition order)"
    return ""


def projection_array(a, name, geometry):
    """``a`` as C-contiguous float32 of ``geometry.shape``; a ValueError naming ``name`` if it is not numeric,
    has another shape or holds NaN/inf."""
    try:
        arr = np.asarray(a)
    except Exception:  # pragma: no cover - exotic inputs
        raise ValueError(f"{name} must be a numeric array") from None
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"{name} must be a numeric array, got dtype {arr.dtype}")
    if arr.shape != geometry.shape:
        raise ValueError(f"{name} has shape {arr.shape} but the geometry needs {expected_shape(geometry, arr.shape)}")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    check_finite(arr, name)
    return arr


def expected_shape(geometry, shape):
    """The projection shape ``geometry`` needs, in words for a message about an array of ``shape``.

    With a hint when ``shape`` looks like several rotations of a geometry given once (a dynamic scan).
    """
    return _shape_words(geometry) + _dynamic_hint(shape, geometry)


def _shape_words(geometry):
    if geometry.ndim == 3:
        return f"(n_angles, rows, cols) = {geometry.shape}"
    return f"(n_angles, det_count) = {geometry.shape}"


def check_finite(arr, name):
    """Raise a ValueError naming ``name`` and counting the NaN and inf values if ``arr`` holds any."""
    bad = ~np.isfinite(arr)
    if bad.any():
        n_nan = int(np.isnan(arr).sum())
        raise ValueError(
            f"{name} contains {int(bad.sum())} non-finite values ({n_nan} NaN, {int(bad.sum()) - n_nan} inf)"
        )


def per_projection_array(t, name, n_angles):
    """``t`` as a ``(n_angles,)`` float64 array (one value per projection: theta, time); a ValueError naming
    ``name`` if it has another shape or holds NaN/inf."""
    try:
        arr = np.asarray(t, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a numeric array") from None
    if arr.ndim != 1 or arr.shape[0] != n_angles:
        raise ValueError(f"{name} has shape {np.shape(t)} but the geometry has {n_angles} projections")
    check_finite(arr, name)
    return arr


def check_contrast(value, name):
    """``value`` as a finite, non-zero float (the bubble contrast, 1/mm); a ValueError naming ``name`` if it is
    missing, not a number, zero or not finite."""
    if value is None:
        raise ValueError(
            f"{name} is required: attenuation of the gas minus that of the liquid, 1/mm (e.g. -0.1)"
        )
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v) or v == 0:
        raise ValueError(f"{name} must be finite and non-zero, got {value!r}")
    return v


def row_window_geometry(geometry, rows, where):
    """The geometry of detector rows ``rows = (start, stop)`` of ``geometry`` (3D only); ``where`` names the
    scan in the messages. The one check of a row window, of a file (:func:`~bubsub.core.io.scanfile.read_scan`)
    or in memory (:meth:`Scan.row_window`)."""
    if geometry.ndim != 3:
        raise ValueError(f"{where}: reading a subset of detector rows needs a 3D scan")
    try:
        start, stop = (int(r) for r in rows)
    except (TypeError, ValueError):
        raise ValueError(f"rows must be (start, stop), got {rows!r}") from None
    if not 0 <= start < stop <= geometry.det_rows:
        raise ValueError(f"{where}: rows ({start}, {stop}) do not lie within the detector's {geometry.det_rows} rows")
    return geometry.window(start, 0, stop - start, geometry.det_cols)


def row_slice(rows):
    """The index of the detector-row axis of a 3D dataset: all rows, or the slice ``rows``."""
    return slice(None) if rows is None else slice(int(rows[0]), int(rows[1]))
