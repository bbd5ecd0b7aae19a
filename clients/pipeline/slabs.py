"""Slabs of detector rows: a tall parallel-beam scan reconstructed piece by piece.

In a parallel-beam scan whose detector rows are perpendicular to the
rotation axis, each row sees one slice of the sample, so the scan splits
exactly into slabs of rows. Each slab is one task:

1. it reads only its rows from the scan file (:func:`bubsub.core.io.scanfile.read_scan`
   with ``rows=``: HDF5 hyperslabs; no process holds the whole scan), or cuts
   them from a scan in memory (:meth:`Scan.row_window`, a 4D subscan): the rows
   it *owns* (its core) and a *halo* of rows above and below, at least the
   largest bubble's radius wide (:func:`slab_scan`);
2. it reconstructs them with the full pipeline (:func:`~bubsub.clients.pipeline.reconstruct.reconstruct`)
   in coordinates centred on the rows read (:meth:`ScanGeometry.translated`),
   so every stage sees an ordinary, smaller scan: bubbles reaching into the
   halo are fitted there against the data they really produce, with the
   neighbours' bubbles of the halo fitted beside them as known signal;
3. it keeps, in world coordinates, every bubble with its centroid's
   distance to the rows read.

:func:`stitch` then keeps each bubble once: the bubbles whose centroid lies
in their slab's core, of two such bubbles of neighbouring slabs at the same
place (a centroid on a seam) the one further from its slab's edge, and a
bubble whose centroid fell into the halo of both slabs (claimed by neither)
from the slab that saw it whole. A bubble is therefore never lost,
duplicated or cut at a seam as long as the halo holds the bubbles whose
centres are in the core (the report counts the kept bubbles that reach a
slab's read edge, ``seam_cut``; zero says the halo was wide enough).

Bubbles of known identity (the warm starts of a 4D subscan, each with its
track id) are fitted slab by slab with :func:`fit_known`: each slab fits the
bubbles whose starting centroid lies in its rows read, and keeps those whose
starting centroid lies in its core. Ownership by the starting centroid needs
no matching and gives every bubble exactly one slab however far its fit moves
it: the cores partition the detector and each lies within its rows read.

The slabs run one after another in this process (``client=None``) or as
Dask tasks (:func:`bubsub.clients.cluster.engine.run_tasks`); each finished
slab is written to ``OUT/slabs/`` at once, so ``resume=True`` continues
after a crash or Ctrl-C from the slabs already done. Memory is one slab's,
whatever the number of slabs.

One module of about 800 lines on purpose: the plan, the slab task, the
stitching and ownership rules and the checkpoints must agree on one slab
layout (core, read rows, origin, ownership heights); keeping them together
keeps it in one place.

Cone beam: the rows of a cone-beam detector are not slices of the sample
(the rays diverge), so :func:`check_slab_geometry` refuses it; such a scan
is reconstructed whole.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from bubsub.core.io.atomic import atomic_path
from bubsub.core.projection.mesh import Mesh, equivalent_radius
from bubsub.core.projection.subdivision import SubdivisionSurface

from bubsub.clients.pipeline.resolution import level_counts

__all__ = ["Slab", "SlabResult", "plan_slabs", "check_slab_geometry", "slab_origin", "default_slab_rows",
           "auto_slabs", "slab_count", "estimate_halo", "known_halo", "halo_rows", "slab_scan", "slab_bounds", "run_slab", "stitch",
           "stitch_previews", "fit_known", "slab_totals", "reconstruct_slabs", "SLAB_PIXELS", "WHOLE_SCAN_SLABS",
           "OBJECTIVE_NOTE"]

#: Detector pixels (projections x rows x columns) read by one slab when the number of slabs is chosen
#: automatically. A slab of this size with ~600 bubbles reconstructs in under a gigabyte (the ~600-bubble
#: column of ``bubsub bench scale``, 7.9 million pixels, whole: docs/scale.md); smaller slabs cost more
#: than they save: each reads its halos again and fits the bubbles there a second time (that column in
#: three slabs of 3 million pixels read 440 of its 256 rows and took twice as long as whole).
SLAB_PIXELS = 8_000_000

#: A scan of up to this many times :data:`SLAB_PIXELS` pixels is one slab by default.
WHOLE_SCAN_SLABS = 1.25

#: Least core rows of a slab, in halos: thinner slabs spend most of their work on the halo.
MIN_CORE_HALOS = 2

_FORMAT = 1


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


def _row_height(geometry, slab, row):
    """Height along the row direction of the edge between rows ``row - 1`` and ``row`` (mm, 0 at the
    detector's centre)."""
    return (row - 0.5 * slab.detector_rows) * _pixel(geometry)


def slab_bounds(geometry, slab):
    """Heights along the row direction (mm, 0 at the detector's centre) of a slab's core and rows read:
    ``(core_lo, core_hi, read_lo, read_hi)``, infinite where they reach the detector's edge (a centroid
    beyond the first or last row still belongs to the end slab)."""
    core_lo = -np.inf if slab.first else _row_height(geometry, slab, slab.core[0])
    core_hi = np.inf if slab.last else _row_height(geometry, slab, slab.core[1])
    read_lo = -np.inf if slab.read[0] == 0 else _row_height(geometry, slab, slab.read[0])
    read_hi = np.inf if slab.read[1] == slab.detector_rows else _row_height(geometry, slab, slab.read[1])
    return core_lo, core_hi, read_lo, read_hi


def _axis(geometry):
    v = geometry.vectors[0, 9:12]
    return v / np.linalg.norm(v)


def _pixel(geometry):
    """A detector row's height, mm."""
    return float(np.linalg.norm(geometry.vectors[0, 9:12]))


def _moved(surface, offset):
    return surface.with_vertices(np.asarray(surface.vertices) + offset)


def _is_scan(source):
    from bubsub.core.io.scanfile import Scan

    return isinstance(source, Scan)


def _geometry_of(source):
    """The whole scan's geometry: of the scan in memory, or read from the file without its projections."""
    from bubsub.core.io.scanfile import read_geometry

    return source.geometry if _is_scan(source) else read_geometry(source)


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
    from bubsub.core.io.scanfile import read_scan

    if _is_scan(source):
        part = source.row_window(slab.read)
        if bubble_contrast is not None:
            part = replace(part, bubble_contrast=bubble_contrast)
    else:
        part = read_scan(source, bubble_contrast=bubble_contrast, rows=slab.read)
    origin = slab_origin(part.geometry, slab)
    return replace(part, geometry=part.geometry.translated(origin), path=None), origin


def run_slab(source, slab, settings, bubble_contrast=None, server=None, token=None):
    """Reconstruct one slab (a task: module-level, picklable arguments, small result).

    Parameters
    ----------
    source : str, Path or Scan
        The scan file, of which only the slab's rows are read, or the scan in memory.
    slab : Slab
    settings : ReconstructionSettings
    bubble_contrast : float, optional
        As :func:`read_scan`'s.
    server, token : str, optional
        A projector server to fit against (each slab a fitting job of its own).

    Returns
    -------
    SlabResult
    """
    from bubsub.clients.pipeline.reconstruct import reconstruct

    local, origin = slab_scan(source, slab, bubble_contrast)
    factory, client, jobs = None, None, []
    if server is not None:
        from bubsub.clients.remote.client import connect

        client = connect(server, token)

        def factory(geometry, data, surfaces):
            job = client.create_job(geometry, data=data, surfaces=surfaces, supersampling=settings.supersampling)
            jobs.append(job)
            return job
    try:
        rec = reconstruct(local, settings, projector_factory=factory)
    finally:
        if client is not None:
            for job in jobs:
                try:
                    job.delete()
                except Exception:  # noqa: BLE001 - the slab's result matters more than the server's clean-up
                    pass
            client.close()
    report = dict(rec.report, origin_mm=origin.tolist(), core_rows=list(slab.core), read_rows=list(slab.read))
    part, extent = _core_preview(rec, local.geometry, slab, origin)
    return SlabResult(slab, [_moved(s, origin) for s in rec.surfaces], report, part, extent)


def _core_preview(rec, geometry, slab, origin):
    """The slices of a slab's preview (local coordinates) whose centres lie in its core, in world coordinates."""
    if rec.preview is None or rec.preview.ndim != 3:
        return None, None
    image, (x0, x1, y0, y1, z0, z1) = rec.preview, rec.preview_extent
    dz = (z1 - z0) / image.shape[0]
    z = z0 + (np.arange(image.shape[0]) + 0.5) * dz + float(origin[2])
    lo = -np.inf if slab.first else _row_height(geometry, slab, slab.core[0])
    hi = np.inf if slab.last else _row_height(geometry, slab, slab.core[1])
    keep = np.nonzero((z >= lo) & (z < hi))[0]
    if len(keep) == 0:
        return None, None
    return (np.ascontiguousarray(image[keep[0]:keep[-1] + 1], dtype=np.float32),
            (x0, x1, y0, y1, float(z[keep[0]] - 0.5 * dz), float(z[keep[-1]] + 0.5 * dz)))


def stitch_previews(results):
    """One preview from the slabs' core slices (for the overlay picture), or ``(None, None)``.

    Slabs share the preview's voxel size (it follows the field of view's radius), so their
    slices stack; the extent runs from the first part's bottom over all slices stacked.
    """
    parts = [(r.preview, r.preview_extent) for r in results if r.preview is not None]
    if not parts or len({p.shape[1:] for p, _ in parts}) != 1:
        return None, None
    image = np.concatenate([p for p, _ in parts])
    e0 = parts[0][1]
    dz = (e0[5] - e0[4]) / parts[0][0].shape[0]
    return image, (*e0[:4], e0[4], e0[4] + dz * image.shape[0])


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
    from bubsub.clients.pipeline.initial import initial_centres
    from bubsub.clients.pipeline.preview import voxel_preview

    n = min(STRIP_ROWS, geometry.det_rows)
    start = (geometry.det_rows - n) // 2
    strip = Slab(0, (start, start + n), (start, start + n), geometry.det_rows)
    scan, _ = slab_scan(source, strip, bubble_contrast)
    image, extent = voxel_preview(scan.bubble_data, scan.geometry, scan.bubble_contrast, settings.voxel_size,
                                  method=settings.preview)
    _, radii = initial_centres(image, extent, detector="dt", contrast=scan.bubble_contrast)
    if len(radii) == 0:
        return max(2, geometry.det_rows // 10)
    return halo_rows(float(np.percentile(radii, 95)), _pixel(geometry))


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
    reach = max((max(hi - z, z - lo) for _, _, z, lo, hi in _bubble_heights(surfaces, geometry)), default=0.0)
    return halo_rows(reach, _pixel(geometry))


def halo_rows(radius, pixel):
    """Halo rows for bubbles of up to ``radius`` (mm) on rows ``pixel`` (mm) high: :data:`HALO_OVER_RADIUS`
    times the radius in rows, plus two (the rule of :func:`estimate_halo` and :func:`known_halo`)."""
    return int(np.ceil(HALO_OVER_RADIUS * radius / pixel)) + 2


def _bubble_heights(surfaces, geometry):
    """Per bubble: centroid (mm), equivalent radius (mm), the heights along the row direction of its centroid
    and of its lowest and highest points (mm)."""
    axis = _axis(geometry)
    out = []
    for s in surfaces:
        fine = s.fine()
        c = np.asarray(fine.centroid, dtype=float)
        h = np.asarray(fine.vertices) @ axis
        out.append((c, equivalent_radius(abs(fine.volume), 3), float(c @ axis), float(h.min()), float(h.max())))
    return out


def stitch(results, geometry):
    """One list of bubbles from the slabs' results, each bubble kept once (rules in the module docstring).

    Parameters
    ----------
    results : list of SlabResult
        In slab order.
    geometry : ScanGeometry
        The whole scan's.

    Returns
    -------
    surfaces : list of SubdivisionSurface
        Sorted by height along the rotation axis.
    summary : dict
        ``owned`` (bubbles whose centroid lies in their slab's core), ``duplicates_dropped``
        (the same bubble owned by two slabs), ``claimed_from_halo`` (a bubble no slab owned, kept
        from the one that saw it whole), ``seam_cut`` (kept bubbles reaching a slab's read edge
        inside the detector: the halo was too narrow for them).
    """
    axis = _axis(geometry)
    pixel = _pixel(geometry)
    rows = []  # (slab, index, centroid, radius, interior distance, owned, cut by an inner read edge)
    for res in results:
        core_lo, core_hi, read_lo, read_hi = slab_bounds(geometry, res.slab)
        for i, (c, r, z, lo, hi) in enumerate(_bubble_heights(res.surfaces, geometry)):
            interior = min(lo - read_lo, read_hi - hi)
            rows.append((res.slab.index, i, c, r, interior, core_lo <= z < core_hi, interior < pixel))
    by_slab = {res.slab.index: res for res in results}
    owned = [row for row in rows if row[5]]
    # the same bubble owned by two neighbouring slabs (its centroid estimates on both sides of the seam)
    owned.sort(key=lambda row: -row[4])
    kept, dropped = [], 0
    for row in owned:
        if _same_bubble(row, kept):
            dropped += 1
            continue
        kept.append(row)
    claimed = 0
    for row in sorted((row for row in rows if not row[5] and not row[6]), key=lambda row: -row[4]):
        if not _same_bubble(row, kept):
            kept.append(row)
            claimed += 1
    kept.sort(key=lambda row: (float(row[2] @ axis), row[0], row[1]))
    surfaces = [by_slab[k].surfaces[i] for k, i, *_ in kept]
    return surfaces, {"owned": len(owned) - dropped, "duplicates_dropped": dropped, "claimed_from_halo": claimed,
                      "seam_cut": int(sum(row[6] for row in kept))}


def _same_bubble(row, kept):
    """Whether a kept bubble's centroid lies within half the smaller radius of ``row``'s."""
    if not kept:
        return False
    centres = np.array([k[2] for k in kept])
    radii = np.array([k[3] for k in kept])
    return bool(np.any(np.linalg.norm(centres - row[2], axis=1) < 0.5 * np.minimum(radii, row[3])))


# -- bubbles of known identity ----------------------------------------------------------------------------
def fit_known(source, surfaces, fit, plan):
    """Fit bubbles of known identity slab by slab (the warm starts of a 4D subscan; rules in the module docstring).

    Parameters
    ----------
    source : str, Path or Scan
        The scan file or the scan in memory; each slab reads its rows (:func:`slab_scan`).
    surfaces : list of SubdivisionSurface
        The bubbles' starts, world coordinates.
    fit : callable(geometry, data, surfaces) -> (list of SubdivisionSurface, dict)
        Fits surfaces to data in a slab's coordinates; the dict is its report (``iterations``,
        ``stop_reason``, ``interrupted``, ...). An error it raises ends the whole fit.
    plan : list of Slab
        :func:`plan_slabs` of the scan's rows.

    Returns
    -------
    fitted : list of SubdivisionSurface
        World coordinates, in the order of ``surfaces``, each from the slab that owns it; after an
        interrupted slab, the bubbles of the slabs not fitted are their starts.
    entries : list of dict
        Per slab (up to an interrupted one): its rows, its fit's report, ``bubbles`` (owned),
        ``bubbles_fitted`` (owned and from the halo), ``seconds_total`` (reading and fitting).
    summary : dict
        ``owned`` (bubbles kept from their slab), ``left_core`` (of them, fitted outside their slab's core:
        kept all the same), ``seam_cut`` (kept bubbles reaching their slab's read edge inside the detector:
        the halo was too narrow for them).
    """
    geometry = _geometry_of(source)
    pixel = _pixel(geometry)
    start = [z for _, _, z, _, _ in _bubble_heights(surfaces, geometry)]
    bounds = [slab_bounds(geometry, sl) for sl in plan]
    owner = [next(k for k, (lo, hi, _, _) in enumerate(bounds) if lo <= z < hi) for z in start]
    fitted, entries, summary = list(surfaces), [], {"owned": 0, "left_core": 0, "seam_cut": 0}
    for k, sl in enumerate(plan):
        t0 = time.perf_counter()
        core_lo, core_hi, read_lo, read_hi = bounds[k]
        mine = [i for i, z in enumerate(start) if read_lo <= z < read_hi]
        if mine:
            local, origin = slab_scan(source, sl)
            out, report = fit(local.geometry, local.bubble_data, [_moved(surfaces[i], -origin) for i in mine])
        else:
            out, report = [], {"iterations": 0, "stop_reason": "no bubbles"}
        owned = [i for i in mine if owner[i] == k]
        for i, s in zip(mine, out):
            if owner[i] == k:
                fitted[i] = _moved(s, origin)
        for _, _, z, lo, hi in _bubble_heights([fitted[i] for i in owned], geometry):
            summary["left_core"] += not core_lo <= z < core_hi
            summary["seam_cut"] += min(lo - read_lo, read_hi - hi) < pixel
        summary["owned"] += len(owned)
        entries.append({**_rows_entry(sl), **report, "bubbles": len(owned), "bubbles_fitted": len(mine),
                        "seconds_total": time.perf_counter() - t0})
        if report.get("interrupted"):
            break
    return fitted, entries, summary


def _rows_entry(slab):
    """How a slab's entry in ``report.json`` names it."""
    return {"index": slab.index, "core_rows": list(slab.core), "read_rows": list(slab.read)}


def slab_totals(reports, keys):
    """The slabs' reports summed over ``keys``, ``interrupted`` when one was, and their stop reasons joined."""
    interrupted = any(r.get("interrupted") for r in reports)
    totals = {k: sum(r.get(k) or 0 for r in reports) for k in keys}
    totals.update(interrupted=interrupted, stop_reason="interrupted" if interrupted else
                  "; ".join(sorted({str(r.get("stop_reason")) for r in reports})))
    return totals


# -- checkpoints ------------------------------------------------------------------------------------------
def slab_key(scan_path, slab, settings):
    """What a finished slab's checkpoint must match to be reused by ``resume``: the scan file (path, size,
    modification time), the slab's rows and every setting."""
    p = Path(scan_path).resolve()
    st = p.stat()
    doc = {"scan": str(p), "size": st.st_size, "mtime_ns": st.st_mtime_ns, "slab": [slab.core, slab.read,
           slab.detector_rows], "settings": {k: v for k, v in vars(settings).items() if k != "progress"},
           "format": _FORMAT}
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()


def write_slab(path, result, key):
    """Write a :class:`SlabResult` atomically (``.npz``: control meshes, levels, report as JSON)."""
    from bubsub.clients.pipeline.outputs import json_default

    surfaces = result.surfaces
    arrays = {
        "key": np.array(key),
        "slab": np.array([result.slab.index, *result.slab.core, *result.slab.read, result.slab.detector_rows]),
        "report": np.array(json.dumps(result.report, default=json_default)),
        "n_vertices": np.array([len(s.vertices) for s in surfaces], dtype=np.int64),
        "n_faces": np.array([len(s.control_faces) for s in surfaces], dtype=np.int64),
        "levels": np.array([s.levels for s in surfaces], dtype=np.int64),
        "attenuation": np.array([s.attenuation for s in surfaces], dtype=float),
        "vertices": np.concatenate([s.vertices for s in surfaces]) if surfaces else np.zeros((0, 3)),
        "faces": np.concatenate([s.control_faces for s in surfaces]) if surfaces else np.zeros((0, 3), np.int64),
    }
    if result.preview is not None:
        arrays["preview"], arrays["preview_extent"] = result.preview, np.asarray(result.preview_extent, dtype=float)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def read_slab(path, key=None):
    """A checkpoint of :func:`write_slab`, or None when it is missing, unreadable or was made with another key."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if key is not None and str(z["key"]) != key:
                return None
            idx, c0, c1, r0, r1, n_rows = (int(x) for x in z["slab"])
            report = json.loads(str(z["report"]))
            v_end, f_end = np.cumsum(z["n_vertices"]), np.cumsum(z["n_faces"])
            surfaces = []
            for k in range(len(v_end)):
                v = z["vertices"][v_end[k] - z["n_vertices"][k]:v_end[k]]
                f = z["faces"][f_end[k] - z["n_faces"][k]:f_end[k]]
                surfaces.append(SubdivisionSurface(Mesh(v, f, float(z["attenuation"][k])), int(z["levels"][k])))
            preview = np.array(z["preview"]) if "preview" in z else None
            extent = tuple(float(x) for x in z["preview_extent"]) if "preview_extent" in z else None
    except (OSError, ValueError, KeyError):
        return None
    return SlabResult(Slab(idx, (c0, c1), (r0, r1), n_rows), surfaces, report, preview, extent)


# -- the whole scan ---------------------------------------------------------------------------------------
def reconstruct_slabs(source, settings=None, *, slabs=None, halo=None, client=None, out=None, resume=False,
                      server=None, token=None, bubble_contrast=None):
    """Reconstruct a scan slab by slab and stitch the bubbles (see the module docstring).

    Parameters
    ----------
    source : str, Path or Scan
        The scan file, of which each slab reads its rows, or a scan in memory (a 4D subscan), which every
        task receives whole (on a cluster, give the file).
    settings : ReconstructionSettings, optional
        Each slab's.
    slabs : int, optional
        Number of slabs; default :func:`auto_slabs`.
    halo : int, optional
        Halo rows; default :func:`estimate_halo`.
    client : dask.distributed.Client, optional
        Run the slabs as tasks on its cluster; None runs them here, one after the other.
    out : str or Path, optional
        Folder whose ``slabs/`` subfolder receives each finished slab's checkpoint (a scan file only: the
        checkpoints' key names it).
    resume : bool
        Reuse the checkpoints in ``out/slabs`` made with the same scan, rows and settings.
    server, token : str, optional
        Fit every slab against this projector server.
    bubble_contrast : float, optional

    Returns
    -------
    Reconstruction
        ``report["slabs"]`` has each slab's rows, bubbles, seconds and stop reason;
        ``report["stitch"]`` :func:`stitch`'s summary.
    """
    from bubsub.clients.cluster.engine import run_tasks
    from bubsub.clients.pipeline.checks import check_settings
    from bubsub.clients.pipeline.fov import fov_report
    from bubsub.clients.pipeline.reconstruct import Reconstruction, ReconstructionSettings
    from bubsub.clients.progress import phase

    s = settings or ReconstructionSettings()
    t0 = time.perf_counter()
    geometry = _geometry_of(source)
    check_settings(s, geometry.ndim)
    check_slab_geometry(geometry)
    if s.holdout is not None:
        raise ValueError("--holdout is not available with slabs; reconstruct the scan whole (--slabs 1)")
    if out is not None and _is_scan(source):
        raise ValueError("slab checkpoints (out=) need a scan file: their key is the file's")
    if halo is None:
        halo = estimate_halo(source, geometry, s, bubble_contrast)
    if slabs is None:
        slabs = auto_slabs(geometry, halo)
    plan = plan_slabs(geometry.det_rows, slabs, halo)
    folder = None if out is None else Path(out) / "slabs"
    keys = [None if folder is None else slab_key(source, sl, s) for sl in plan]
    results = [None] * len(plan)
    if resume and folder is not None:
        for k, sl in enumerate(plan):
            results[k] = read_slab(folder / f"slab_{sl.index:03d}.npz", keys[k])
    todo = [k for k in range(len(plan)) if results[k] is None]
    task_settings = replace(s, progress=s.progress and client is None and len(plan) == 1)
    with phase(f"slabs ({len(plan)} of {plan[0].core[1] - plan[0].core[0]} rows, halo {halo})", len(plan),
               unit="slab", enabled=s.progress) as bar:
        bar.update(len(plan) - len(todo))

        def done(i, res):
            k = todo[i]
            results[k] = res
            if folder is not None:
                write_slab(folder / f"slab_{plan[k].index:03d}.npz", res, keys[k])
            bar.update(1, bubbles=sum(len(r.surfaces) for r in results if r is not None))

        task_source = source if _is_scan(source) else str(source)
        run_tasks(client, run_slab, [(task_source, plan[k], task_settings, bubble_contrast, server, token)
                                     for k in todo], on_result=done)
    surfaces, summary = stitch(results, geometry)
    preview, extent = stitch_previews(results)
    return Reconstruction(surfaces, _report(results, surfaces, summary, geometry, s, halo, len(todo),
                                            time.perf_counter() - t0, fov_report(geometry)), preview, extent)


#: ``report.json``'s word on the objectives of a slabbed fit.
OBJECTIVE_NOTE = "objectives are sums over the slabs' own objectives (halo rows counted in two slabs)"

_SUMMED = ("iterations", "evaluations", "final_objective", "initial_objective", "bubbles_initial", "bubbles_dropped",
           "seconds_initialisation", "seconds_fit")


def _report(results, surfaces, summary, geometry, settings, halo, computed, seconds, fov):
    """``report.json`` of a slabbed reconstruction."""
    from bubsub.clients.pipeline.reconstruct import merged_projector_report

    per_slab = []
    for res in results:
        r = res.report
        per_slab.append({**_rows_entry(res.slab), "bubbles": r["bubbles"], "stop_reason": r.get("stop_reason"),
                         "seconds_total": r.get("seconds_total"), "seconds_parts": r.get("seconds_parts"),
                         "cpu_seconds_parts": r.get("cpu_seconds_parts"), "iterations": r.get("iterations"),
                         "final_objective": r.get("final_objective"), "fit_levels": r.get("fit_levels"),
                         "preview": r.get("preview")})
    parts, cpu = {}, {}
    for res in results:
        for name, v in (res.report.get("seconds_parts") or {}).items():
            parts[name] = parts.get(name, 0.0) + v
        for name, v in (res.report.get("cpu_seconds_parts") or {}).items():
            cpu[name] = cpu.get(name, 0.0) + v
    report = slab_totals([res.report for res in results], _SUMMED)
    report.update({
        "bubbles": len(surfaces),
        "dimension": 3,
        "subdivision_levels": level_counts(surfaces),
        "slabs": per_slab,
        "slab_halo_rows": halo,
        "slabs_computed": computed,
        "stitch": summary,
        "objective_note": OBJECTIVE_NOTE,
        "seconds_total": seconds,
        "seconds_parts": parts,
        "cpu_seconds_parts": cpu,
        "field_of_view_mm": fov,
        "preview": _stitched_preview(results),
        "projections_used": geometry.n_angles,
        "validity": _merged_validity(results),
        "projector": merged_projector_report([res.report.get("projector") for res in results]),
        "settings": {k: v for k, v in vars(settings).items() if k != "progress"},
    })
    return report


def _stitched_preview(results):
    """The slabs' previews in one entry: the coarsest voxel (each slab chooses its own for its bubbles,
    :func:`.preview.voxel_for_bubbles`; the coarsest is the resolution every slab's contacts rest on, and
    ``bubsub analyse``'s default contact gap), and whether any slab made its preview finer; None for
    reports without it."""
    previews = [res.report.get("preview") for res in results]
    if not previews or any(p is None for p in previews):
        return None
    return {"voxel_mm": max(p["voxel_mm"] for p in previews),
            "finer_for_bubbles": any(p["finer_for_bubbles"] for p in previews)}


def _merged_validity(results):
    found = [v for res in results for v in (res.report.get("validity") or {}).get("violations_remaining", [])]
    return {"violations_found": [], "actions": [], "violations_remaining": found,
            "dropped": sum((res.report.get("validity") or {}).get("dropped", 0) for res in results)}
