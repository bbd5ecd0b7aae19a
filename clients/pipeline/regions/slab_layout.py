"""The layout of slabs of detector rows: which rows each slab owns and reads, where its coordinates sit,
and how wide its halo is.

Every other slab module (:mod:`.slabs` runs them, :mod:`.slab_stitch` keeps each bubble once) works on
this one layout: a slab's *core* (the rows it owns; the cores partition the detector), its rows *read*
(the core and a *halo* above and below), its *origin* (the centre of its rows read, where its own
coordinates are centred) and the heights along the row direction of these rows' edges, against which a
bubble's centroid decides its owner.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from bubsub.core.io.scanfile import Scan, read_geometry, read_scan
from bubsub.core.projection.mesh import equivalent_radius

from bubsub.clients.pipeline.static.initial import initial_centres
from bubsub.clients.pipeline.static.preview import voxel_preview

__all__ = ["Slab", "SlabResult", "plan_slabs", "check_slab_geometry", "slab_origin", "default_slab_rows",
           "auto_slabs", "slab_count", "estimate_halo", "known_halo", "halo_rows", "slab_scan", "slab_bounds",
           "edge_height", "row_axis", "row_pitch", "moved", "is_scan", "scan_geometry", "bubble_heights",
           "SLAB_PIXELS", "WHOLE_SCAN_SLABS", "MIN_CORE_HALOS", "HALO_OVER_RADIUS", "STRIP_ROWS"]

#: Detector pixels (projections x rows x columns) read by one slab when the number of slabs is chosen
#: automatically. A slab of this size with ~600 bubbles reconstructs in under a gigabyte (the ~600-bubble
#: column of ``bubsub bench scale``, 7.9 million pixels, whole: docs/scale.md); smaller slabs cost more
#: than they save: each reads its halos again and fits the bubbles there a second time (docs/large-scans.md
#: measures it on that column).
SLAB_PIXELS = 8_000_000

#: A scan of up to this many times :data:`SLAB_PIXELS` pixels is one slab by default.
WHOLE_SCAN_SLABS = 1.25

#: Least core rows of a slab, in halos: thinner slabs spend most of their work on the halo.
MIN_CORE_HALOS = 2

@dataclass(frozen=True)
class Slab:
    """One slab of detector rows.

    Attributes
    ----------
    index : int
    core : (int, int)
        Rows ``[start, stop)`` it owns.
    read : (int, int)
        Rows ``[start, stop)`` it reads: the core and its halo, on the detector.
    detector_rows : int
        Rows of the whole detector.
    """

    index: int
    core: tuple
    read: tuple
    detector_rows: int

    def __repr__(self):
        return f"Slab({self.index}, core={self.core}, read={self.read}, detector_rows={self.detector_rows})"

    @property
    def first(self):
        """Whether the slab starts at the detector's first row."""
        return self.core[0] == 0

    @property
    def last(self):
        """Whether the slab ends at the detector's last row."""
        return self.core[1] == self.detector_rows


@dataclass
class SlabResult:
    """What one slab's task returns: its bubbles in world coordinates, and its report.

    Attributes
    ----------
    slab : Slab
    surfaces : list of SubdivisionSurface
        Every bubble the slab reconstructed (not only those it owns).
    report : dict
        :func:`~bubsub.clients.pipeline.reconstruct.reconstruct`'s report, plus ``origin_mm``.
    preview : ndarray float32 ``(slices, rows, cols)``, optional
        The slices of the slab's voxel preview that lie in its core (for the overlay picture).
    preview_extent : tuple, optional
        Their extent in world coordinates, mm.
    """

    slab: Slab
    surfaces: list
    report: dict
    preview: np.ndarray | None = None
    preview_extent: tuple | None = None


def check_slab_geometry(geometry):
    """Refuse a geometry whose detector rows are not slices of the sample.

    Raises
    ------
    ValueError
        For 2D and cone-beam geometries, and parallel-beam ones whose row
        direction changes between projections or is not perpendicular to the rays.
    """
    if geometry.ndim != 3:
        raise ValueError("slabs of detector rows need a 3D scan; leave --slabs out for a 2D one")
    if geometry.is_cone:
        raise ValueError("slabs need a parallel-beam scan: the rows of a cone-beam detector are not slices of the "
                         "sample; reconstruct it whole (--slabs 1)")
    vec = geometry.vectors
    ray, v = vec[:, 0:3], vec[:, 9:12]
    if not np.allclose(v, v[0], rtol=0, atol=1e-9 * np.linalg.norm(v[0])):
        raise ValueError("slabs need a detector whose row direction (v) is the same in every projection")
    cos = np.abs(np.einsum("ij,ij->i", ray, v)) / (np.linalg.norm(ray, axis=1) * np.linalg.norm(v, axis=1))
    if cos.max() > 1e-6:
        raise ValueError("slabs need rays perpendicular to the detector's row direction (v)")


def plan_slabs(n_rows, slabs, halo):
    """Split ``n_rows`` detector rows into ``slabs`` slabs of nearly equal cores and their halos.

    Parameters
    ----------
    n_rows : int
    slabs : int
        Number of slabs (at most ``n_rows``).
    halo : int
        Rows read above and below each core (clipped to the detector).

    Returns
    -------
    list of Slab
    """
    for name, value, least in (("n_rows", n_rows, 1), ("slabs", slabs, 1), ("halo", halo, 0)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
    if slabs > n_rows:
        raise ValueError(f"cannot split {n_rows} rows into {slabs} slabs")
    edges = np.linspace(0, n_rows, slabs + 1).round().astype(int)
    return [Slab(k, (int(a), int(b)), (int(max(0, a - halo)), int(min(n_rows, b + halo))), int(n_rows))
            for k, (a, b) in enumerate(zip(edges[:-1], edges[1:]))]


def default_slab_rows(geometry, halo, pixels=SLAB_PIXELS):
    """Core rows of a slab that reads about ``pixels`` detector pixels, and at least
    :data:`MIN_CORE_HALOS` halos."""
    per_row = geometry.n_angles * geometry.det_cols
    return max(MIN_CORE_HALOS * halo, int(pixels // per_row) - 2 * halo, 1)


def auto_slabs(geometry, halo, pixels=SLAB_PIXELS):
    """How many slabs a scan gets by default: one unless its detector is much taller than one slab's
    :func:`default_slab_rows` (cone-beam and 2D scans: always one)."""
    if geometry.ndim != 3 or geometry.is_cone:
        return 1
    core = default_slab_rows(geometry, halo, pixels)
    return max(1, int(round(geometry.det_rows / core)))


def slab_count(source, geometry, settings, slabs=None, halo=None, *, whole_needed=False, workers=None):
    """The number of slabs and halo rows a reconstruction of ``source`` uses.

    Parameters
    ----------
    source : str, Path or Scan
        The scan file, or the scan in memory (for :func:`estimate_halo`).
    geometry : ScanGeometry
        The whole scan's.
    settings : ReconstructionSettings
    slabs : int or None
        Asked for (``--slabs N``); None: :func:`auto_slabs`, one slab for scans of at most
        :data:`WHOLE_SCAN_SLABS` x :data:`SLAB_PIXELS` pixels, cone-beam and 2D scans, and when ``whole_needed``.
    halo : int or None
        Asked for (``--slab-halo``); None: :func:`estimate_halo` when there are several slabs.
    whole_needed : bool
        An option that needs the whole scan at once (``--init``, ``--holdout``).
    workers : int, optional
        Workers of the cluster the slabs will run on: ``auto`` then gives the scan at least one slab per
        worker (each core still at least :data:`MIN_CORE_HALOS` halos), so that ``--workers N`` spreads
        a scan that would be one slab in this process.

    Returns
    -------
    (int, int)
        Slabs and halo rows (0 for one slab).

    Raises
    ------
    ValueError
        For several slabs of a geometry :func:`check_slab_geometry` refuses, or with ``whole_needed``.
    """
    if slabs == 1:
        return 1, 0
    spread = slabs is None and workers is not None and workers > 1
    if slabs is None:
        if whole_needed or geometry.ndim != 3 or geometry.is_cone:
            return 1, 0
        if not spread and geometry.n_angles * geometry.det_rows * geometry.det_cols <= WHOLE_SCAN_SLABS * SLAB_PIXELS:
            return 1, 0
    elif whole_needed:
        raise ValueError("--init and --holdout need the scan reconstructed whole (--slabs 1)")
    check_slab_geometry(geometry)
    if halo is None:
        halo = estimate_halo(source, geometry, settings)
    if slabs is not None:
        return int(slabs), int(halo)
    n = auto_slabs(geometry, halo)
    if spread:
        n = max(n, min(int(workers), geometry.det_rows // max(1, MIN_CORE_HALOS * halo)))
    return (n, int(halo)) if n > 1 else (1, 0)


def slab_origin(geometry, slab):
    """World position (mm) of the centre of a slab's rows read, its coordinate origin: the detector's
    centre moved along the row direction ``v`` of ``geometry`` (the whole detector's, or the slab's window)."""
    v = geometry.vectors[0, 9:12]
    return (0.5 * (slab.read[0] + slab.read[1]) - 0.5 * slab.detector_rows) * v


def edge_height(geometry, slab, row):
    """Height along the row direction of the edge between rows ``row - 1`` and ``row`` (mm, 0 at the
    detector's centre)."""
    return (row - 0.5 * slab.detector_rows) * row_pitch(geometry)


def slab_bounds(geometry, slab):
    """Heights along the row direction (mm, 0 at the detector's centre) of a slab's core and rows read:
    ``(core_lo, core_hi, read_lo, read_hi)``, infinite where they reach the detector's edge (a centroid
    beyond the first or last row still belongs to the end slab)."""
    core_lo = -np.inf if slab.first else edge_height(geometry, slab, slab.core[0])
    core_hi = np.inf if slab.last else edge_height(geometry, slab, slab.core[1])
    read_lo = -np.inf if slab.read[0] == 0 else edge_height(geometry, slab, slab.read[0])
    read_hi = np.inf if slab.read[1] == slab.detector_rows else edge_height(geometry, slab, slab.read[1])
    return core_lo, core_hi, read_lo, read_hi


def row_axis(geometry):
    v = geometry.vectors[0, 9:12]
    return v / np.linalg.norm(v)


def row_pitch(geometry):
    """A detector row's height, mm."""
    return float(np.linalg.norm(geometry.vectors[0, 9:12]))


def moved(surface, offset):
    return surface.with_vertices(np.asarray(surface.vertices) + offset)


def is_scan(source):
    return isinstance(source, Scan)


def scan_geometry(source):
    """The whole scan's geometry: of the scan in memory, or read from the file without its projections."""
    return source.geometry if is_scan(source) else read_geometry(source)


def slab_scan(source, slab, bubble_contrast=None):
    """A slab's rows read, in its own coordinates (centred on them, :meth:`ScanGeometry.translated`).

    Parameters
    ----------
    source : str, Path or Scan
        A scan file, of which only the slab's rows are read (HDF5 hyperslabs), or a scan in memory, of
        which :meth:`Scan.row_window` cuts the same rows.
    slab : Slab
    bubble_contrast : float, optional
        As :func:`read_scan`'s.

    Returns
    -------
    scan : Scan
        ``path`` None.
    origin : (3,) float
        The slab's origin in world coordinates, mm (:func:`slab_origin`).
    """
    if is_scan(source):
        part = source.row_window(slab.read)
        if bubble_contrast is not None:
            part = replace(part, bubble_contrast=bubble_contrast)
    else:
        part = read_scan(source, bubble_contrast=bubble_contrast, rows=slab.read)
    origin = slab_origin(part.geometry, slab)
    return replace(part, geometry=part.geometry.translated(origin), path=None), origin


#: Halo over the largest bubble radius the strip preview of :func:`estimate_halo` finds: its distance-transform
#: radii are inscribed radii, short of an elongated bubble's half-length.
HALO_OVER_RADIUS = 1.5

#: Rows of the central strip :func:`estimate_halo` previews.
STRIP_ROWS = 96


def estimate_halo(source, geometry, settings, bubble_contrast=None):
    """Halo rows for the slabs of a scan: :data:`HALO_OVER_RADIUS` times the largest bubble radius in a voxel
    preview of the detector's central :data:`STRIP_ROWS` rows (read alone), plus two rows.

    Parameters
    ----------
    source : str, Path or Scan
        The scan file (only the strip's rows are read) or the scan in memory.
    geometry : ScanGeometry
        The whole scan's.
    settings : ReconstructionSettings
    bubble_contrast : float, optional

    Returns
    -------
    int
    """
    n = min(STRIP_ROWS, geometry.det_rows)
    start = (geometry.det_rows - n) // 2
    strip = Slab(0, (start, start + n), (start, start + n), geometry.det_rows)
    scan, _ = slab_scan(source, strip, bubble_contrast)
    image, extent = voxel_preview(scan.bubble_data, scan.geometry, scan.bubble_contrast, settings.voxel_size,
                                  method=settings.preview)
    _, radii = initial_centres(image, extent, detector="dt", contrast=scan.bubble_contrast)
    if len(radii) == 0:
        return max(2, geometry.det_rows // 10)
    return halo_rows(float(np.percentile(radii, 95)), row_pitch(geometry))


def known_halo(surfaces, geometry):
    """Halo rows for the slabs of a scan whose bubbles are known (the warm starts of a 4D subscan): the rule of
    :func:`estimate_halo` with the bubbles' own extent for the preview's radii, :data:`HALO_OVER_RADIUS` times
    the largest distance along the row direction from a bubble's centroid to its surface, plus two rows.

    Parameters
    ----------
    surfaces : list of SubdivisionSurface
        World coordinates.
    geometry : ScanGeometry

    Returns
    -------
    int
    """
    reach = max((max(hi - z, z - lo) for _, _, z, lo, hi in bubble_heights(surfaces, geometry)), default=0.0)
    return halo_rows(reach, row_pitch(geometry))


def halo_rows(radius, pixel):
    """Halo rows for bubbles of up to ``radius`` (mm) on rows ``pixel`` (mm) high: :data:`HALO_OVER_RADIUS`
    times the radius in rows, plus two (the rule of :func:`estimate_halo` and :func:`known_halo`)."""
    return int(np.ceil(HALO_OVER_RADIUS * radius / pixel)) + 2


def bubble_heights(surfaces, geometry):
    """Per bubble: centroid (mm), equivalent radius (mm), the heights along the row direction of its centroid
    and of its lowest and highest points (mm)."""
    axis = row_axis(geometry)
    out = []
    for s in surfaces:
        fine = s.fine()
        c = np.asarray(fine.centroid, dtype=float)
        h = np.asarray(fine.vertices) @ axis
        out.append((c, equivalent_radius(abs(fine.volume), 3), float(c @ axis), float(h.min()), float(h.max())))
    return out
