"""Raw scan readers: Data Exchange HDF5 and folders of TIFF images.

Both give a :class:`RawSource`: the detector shape, the angles (degrees),
the instrument metadata (keV, mm) and methods that read a block of
projections, flats or darks cropped to a region of interest, so a
preparation never holds more than one slab of the raw data in memory.

Data Exchange (``/exchange/data``, ``data_white``, ``data_dark``,
``theta``; metadata at ``/measurement/instrument/monochromator/energy``,
``/measurement/instrument/detector/pixel_size_x|y`` and
``/measurement/instrument/detection_system/distance``; a dataset's
``units`` attribute is honoured, an unknown unit is an error). Without a
``units`` attribute, energy is read as keV, pixel sizes as micrometres
and the distance as millimetres, as in TomoBank files.

TIFF folder: ``proj*.tif[f]``, ``flat*.tif[f]``, ``dark*.tif[f]`` (sorted
by name; a file may hold several pages) and ``angles.txt`` (one angle per
line, degrees).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import h5py
import numpy as np
import tifffile

__all__ = ["RawSource", "open_raw", "UNITS"]

#: Accepted units and their factor to keV / mm.
UNITS = {
    "energy": {"kev": 1.0, "ev": 1e-3, "mev": 1e3},
    "length": {"mm": 1.0, "um": 1e-3, "µm": 1e-3, "micron": 1e-3, "microns": 1e-3, "micrometer": 1e-3,
               "micrometre": 1e-3, "nm": 1e-6, "cm": 10.0, "m": 1e3},
}

_META = {
    "energy_kev": ("/measurement/instrument/monochromator/energy", "energy", "kev"),
    "pixel_size_x_mm": ("/measurement/instrument/detector/pixel_size_x", "length", "um"),
    "pixel_size_y_mm": ("/measurement/instrument/detector/pixel_size_y", "length", "um"),
    "distance_mm": ("/measurement/instrument/detection_system/distance", "length", "mm"),
}


@dataclasses.dataclass(frozen=True)
class RawSource:
    """A raw scan on disk, read lazily.

    Attributes
    ----------
    path : pathlib.Path
    kind : {"hdf5", "tiff"}
    det_shape : (rows, cols) int
    n_projections, n_flats, n_darks : int
    theta : (n_projections,) float
        As stored (degrees unless ``theta_units`` says otherwise).
    theta_units : str
        ``"deg"`` or ``"rad"`` (from the ``units`` attribute, or ``"deg"``).
    metadata : dict
        ``energy_kev``, ``pixel_size_x_mm``, ``pixel_size_y_mm``,
        ``distance_mm`` where the file has them.
    """

    path: Path
    kind: str
    det_shape: tuple
    n_projections: int
    n_flats: int
    n_darks: int
    theta: np.ndarray
    theta_units: str
    metadata: dict
    _files: dict = dataclasses.field(default_factory=dict, repr=False)

    def __repr__(self):
        return (f"open_raw({str(self.path)!r})  # {self.kind}, {self.n_projections} projections of "
                f"{self.det_shape}, {self.n_flats} flats, {self.n_darks} darks")

    def read(self, which, index, rows, cols):
        """Read frames as float32 ``(k, rows, cols)``.

        Parameters
        ----------
        which : {"data", "white", "dark"}
        index : slice
            Frames to read (``slice(start, stop, step)``).
        rows, cols : (int, int)
            ROI bounds (end exclusive).
        """
        rs, cs = slice(*rows), slice(*cols)
        if self.kind == "hdf5":
            name = {"data": "exchange/data", "white": "exchange/data_white", "dark": "exchange/data_dark"}[which]
            with h5py.File(self.path, "r") as f:
                return np.asarray(f[name][index, rs, cs], dtype=np.float32)

        pages = self._files[which]
        idx = range(len(pages))[index]
        return np.stack([_tiff_page(pages[i], tifffile)[rs, cs] for i in idx]).astype(np.float32, copy=False)


def _tiff_page(ref, tifffile):
    path, page = ref
    return np.asarray(tifffile.imread(path, key=page))


def open_raw(path):
    """Open a raw scan (Data Exchange HDF5 file or TIFF folder) and check its layout.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        If datasets are missing, shapes disagree (flats or darks of another
        detector shape), or a metadata unit is unknown.
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"raw scan {str(p)!r} does not exist")
    return _open_tiff(p) if p.is_dir() else _open_hdf5(p)


def _open_hdf5(p):
    try:
        f = h5py.File(p, "r")
    except OSError as exc:
        raise ValueError(f"{str(p)!r} is neither a TIFF folder nor a readable HDF5 file ({exc})") from None
    with f:
        if "exchange/data" not in f:
            hint = " (it is already a prepared scan file)" if "geometry/vectors" in f else ""
            raise ValueError(f"{p.name}: missing dataset '/exchange/data' (the raw projections){hint}")
        data = f["exchange/data"]
        if data.ndim != 3:
            raise ValueError(f"{p.name}: '/exchange/data' must be (projection, row, col), got shape {data.shape}")
        if "geometry/vectors" in f and np.issubdtype(data.dtype, np.floating) and "exchange/data_white" not in f:
            raise ValueError(f"{p.name} is already a prepared scan (it has '/geometry/vectors' and line "
                             f"integrals); give it to bubsub reconstruct directly")
        det = tuple(data.shape[1:])
        counts = {}
        for which, name in (("white", "exchange/data_white"), ("dark", "exchange/data_dark")):
            if name not in f:
                counts[which] = 0
                continue
            ds = f[name]
            shape = ds.shape[1:] if ds.ndim == 3 else ds.shape
            if tuple(shape) != det:
                raise ValueError(f"{p.name}: '/{name}' frames are {tuple(shape)} but the projections are {det}; "
                                 f"flats and darks must come from the same detector and binning")
            if ds.ndim != 3:
                raise ValueError(f"{p.name}: '/{name}' must be (frame, row, col), got shape {ds.shape}")
            counts[which] = ds.shape[0]
        if "exchange/theta" not in f:
            raise ValueError(f"{p.name}: missing dataset '/exchange/theta' (projection angles, degrees)")
        th = f["exchange/theta"]
        theta = np.asarray(th[()], dtype=np.float64).ravel()
        units = _units_attr(th)
        if units in (None, "deg", "degree", "degrees"):
            theta_units = "deg"
        elif units in ("rad", "radian", "radians"):
            theta_units = "rad"
        else:
            raise ValueError(f"{p.name}: '/exchange/theta' has unknown units {units!r} (expected degrees or radians)")
        if theta.shape[0] != data.shape[0]:
            raise ValueError(f"{p.name}: '/exchange/theta' has {theta.shape[0]} angles for {data.shape[0]} projections")
        meta = {}
        for key, (name, kind, default) in _META.items():
            if name in f:
                ds = f[name]
                val = np.asarray(ds[()], dtype=np.float64).ravel()
                if val.size == 0 or not np.isfinite(val[0]) or val[0] <= 0:
                    raise ValueError(f"{p.name}: '{name}' must be a positive number, got {ds[()]!r}")
                unit = _units_attr(ds) or default
                table = UNITS[kind]
                if unit not in table:
                    raise ValueError(f"{p.name}: '{name}' has unknown units {unit!r}; expected one of {sorted(table)}")
                meta[key] = float(val[0]) * table[unit]
        return RawSource(path=p, kind="hdf5", det_shape=det, n_projections=int(data.shape[0]),
                         n_flats=counts["white"], n_darks=counts["dark"], theta=theta, theta_units=theta_units,
                         metadata=meta)


def _units_attr(ds):
    u = ds.attrs.get("units")
    if u is None:
        return None
    if isinstance(u, np.ndarray):
        u = u.ravel()[0] if u.size else ""
    if isinstance(u, bytes):
        u = u.decode()
    return str(u).strip().lower()


def _open_tiff(p):
    def pages(prefix):
        files = sorted(q for q in p.iterdir() if q.name.lower().startswith(prefix)
                       and q.suffix.lower() in (".tif", ".tiff"))
        out = []
        for q in files:
            with tifffile.TiffFile(q) as tf:
                out += [(q, i, tuple(pg.shape)) for i, pg in enumerate(tf.pages)]
        return out

    proj, white, dark = pages("proj"), pages("flat"), pages("dark")
    if not proj:
        raise ValueError(f"{p}: no projection images (proj*.tif) in the folder")
    det = proj[0][2]
    if len(det) != 2:
        raise ValueError(f"{proj[0][0].name}: projections must be 2D greyscale images, got shape {det}")
    for name, lst in (("projection", proj), ("flat", white), ("dark", dark)):
        for q, i, shape in lst:
            if shape != det:
                raise ValueError(f"{q.name} (page {i}): {name} image is {shape} but the first projection is {det}; "
                                 f"flats and darks must come from the same detector and binning")
    angles = p / "angles.txt"
    if not angles.is_file():
        raise ValueError(f"{p}: missing angles.txt (one projection angle per line, degrees)")
    try:
        theta = np.loadtxt(angles, dtype=np.float64, ndmin=1)
    except ValueError as exc:
        raise ValueError(f"{angles}: not a list of numbers ({exc})") from None
    if theta.shape[0] != len(proj):
        raise ValueError(f"{angles.name} has {theta.shape[0]} angles for {len(proj)} projection images")
    files = {k: [(q, i) for q, i, _ in v] for k, v in (("data", proj), ("white", white), ("dark", dark))}
    return RawSource(path=p, kind="tiff", det_shape=det, n_projections=len(proj), n_flats=len(white),
                     n_darks=len(dark), theta=theta, theta_units="deg", metadata={}, _files=files)
