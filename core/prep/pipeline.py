"""``bubsub prepare``: a raw scan (counts, flats, darks, angles) to a scan file.

The steps, in order (each recorded with its parameters in the report):

1. read and check the raw scan (:mod:`.readers`), the options against it
   (ROI inside the detector, binning dividing it, projections in range),
   the angles (monotonic, degrees);
2. flat/dark model of the ROI and bad-pixel map (:mod:`.flats`);
3. rotation-axis search on the flat-corrected data (:mod:`.centre`), and
   the columns cropped symmetric about the axis;
4. pass 1, in slabs of projections: flat/dark correction, bad-pixel
   repair, Paganin phase retrieval (:mod:`.phase`), clamped ``-log``,
   binning, written to the output;
5. pass 2, in slabs of detector rows: stripe removal (:mod:`.stripes`),
   the background (:mod:`.background`) and each projection's offset in air
   (:func:`bubsub.core.prep.offsets.air_offsets`);
6. bubble contrast (given or estimated from a slice) and its sign checked
   against the data;
7. the geometry (ASTRA vectors, axis at the origin) and the attributes.

Memory is bounded by ``slab_mb`` (the raw file is never read whole), the
output is written atomically (a failure or Ctrl-C leaves no file), and a
``<out>.report.json`` lists every step and parameter.

It is one module on purpose: the steps share the open raw file, the flat model, the cropped columns and
the report's list of steps; each step's computation lives in its own module above, and what stays here is
the order and the hand-over between them.
"""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path

import h5py
import numpy as np
from tqdm.auto import tqdm

from bubsub.core.contrast import contrast_sign_error, signal_masses
from bubsub.core.io.atomic import atomic_path, atomic_write_text
from bubsub.core.io.scanfile import create_scan_datasets, set_scan_attrs
import bubsub.core.prep.background as backgrounds
from bubsub.core.prep.background import (chord_background, detector_offsets, envelope_background,
                                         foam_beyond, noise_level, radial_background, reproject_background,
                                         row_geometry, row_phases, sees_air)
from bubsub.core.prep.centre import (center_pair, center_seam, center_sharpest, center_sharpness, center_symmetry,
                                     center_vo, closest_pair)
from bubsub.core.prep.flats import flat_model, minus_log, repair_pixels
from bubsub.core.prep.gains import GAIN_MEDIAN_COLUMNS, stripe_gains
from bubsub.core.prep.offsets import air_offsets, drift_offsets
from bubsub.core.prep.options import check_against_raw, prepare_options
from bubsub.core.prep.phase import paganin_filter, wavelength_mm
from bubsub.core.prep.readers import open_raw
from bubsub.core.prep.stripes import remove_stripes
from bubsub.core.projection.geometry import ScanGeometry

__all__ = ["prepare", "scan_geometry", "checked_theta"]


def checked_theta(source, index, theta_units=None):
    """Selected angles in degrees, checked to be monotonic and not radians by mistake.

    Raises
    ------
    ValueError
        If the angles repeat or turn back (naming where), or look like radians
        although read as degrees.
    """
    th = np.asarray(source.theta, dtype=float)[index]
    units = theta_units or source.theta_units
    if units == "rad":
        th = np.degrees(th)
    d = np.diff(th)
    if not (np.all(d > 0) or np.all(d < 0)):
        sign = np.sign(np.median(d)) or 1.0
        k = int(np.argmax(sign * d <= 0))
        raise ValueError(f"theta is not monotonic within the selected projections: angle {index[k + 1]} is "
                         f"{th[k + 1]:.4g} deg after {th[k]:.4g} deg; select one sweep with --projections "
                         f"START:STOP:STEP")
    span = abs(th[-1] - th[0])
    if theta_units is None and source.theta_units == "deg" and span < 2 * np.pi * 1.01 and th.size > 8:
        raise ValueError(f"theta spans only {span:.4g} 'degrees' over {th.size} projections: these look like "
                         f"radians; pass --theta-units rad if they are (or deg to keep them)")
    return th


def scan_geometry(theta_deg, *, pixel_size, cols, rows=None, axis_column=None, source_origin=None,
                  origin_detector=None):
    """ASTRA vector geometry with the rotation axis at the origin.

    Parameters
    ----------
    theta_deg : (n,) float
    pixel_size : (float, float)
        Output pixel (height, width), mm.
    cols : int
    rows : int, optional
        ``None`` (or 1 with ``rows=None``) gives a 2D geometry.
    axis_column : float, optional
        Column (pixel index) the axis projects to; default the detector centre.
    source_origin, origin_detector : float, optional
        Cone beam distances, mm (else parallel beam).
    """
    a = np.radians(np.asarray(theta_deg, dtype=float))
    ph, pw = pixel_size
    psize = pw if rows is None else (pw, ph)
    if source_origin is None:
        g = ScanGeometry.parallel(a, pixel_size=psize, cols=cols, rows=rows)
    else:
        g = ScanGeometry.cone(a, source_origin=source_origin, origin_detector=origin_detector, pixel_size=psize,
                              cols=cols, rows=rows)
    if axis_column is None:
        return g
    shift = cols / 2 - 0.5 - float(axis_column)
    vec = np.array(g.vectors)
    if g.ndim == 3:
        vec[:, 3:6] += shift * vec[:, 6:9]
        return ScanGeometry.from_astra(g.kind, vec, rows, cols)
    vec[:, 2:4] += shift * vec[:, 4:6]
    return ScanGeometry.from_astra(g.kind, vec, det_count=cols)


def _slabs(n, per):
    return [(a, min(n, a + per)) for a in range(0, n, per)]


def _bar(total, desc, progress):
    if callable(progress):
        return progress(desc, total, unit="projection" if desc.startswith("pass 1") else "row")

    return tqdm(total=total, desc=desc, unit="proj" if desc.startswith("pass 1") else "row", disable=not progress,
                leave=False)


def prepare(raw, out, options=None, *, progress=True):
    """Prepare a raw scan for ``bubsub reconstruct``.

    Parameters
    ----------
    raw : str or os.PathLike
        Data Exchange HDF5 file or TIFF folder (:func:`open_raw`).
    out : str or os.PathLike
        Scan file to write (atomically); ``<out>.report.json`` is written too.
    options : PrepareOptions, optional
        :func:`prepare_options` (defaults if omitted).
    progress : bool or callable
        tqdm progress bars; or ``progress(desc, total, unit=)`` making each pass's progress (a context
        manager with ``update(n)``, e.g. :func:`bubsub.clients.progress.phase`: one line per pass in a log).

    Returns
    -------
    dict
        The report (also in ``<out>.report.json`` and the file's
        ``prepare_report`` attribute).

    Raises
    ------
    ValueError
        Bad input, named, before any heavy work where it can be known then.
    """
    t_start = time.time()
    o = options if options is not None else prepare_options()
    out = Path(out)
    src = open_raw(raw)
    if out.resolve() == Path(src.path).resolve():
        raise ValueError("--out must not be the raw file itself")
    if not out.parent.is_dir():
        raise ValueError(f"directory {str(out.parent)!r} of --out does not exist")
    rows, cols, index = check_against_raw(o, src.det_shape, src.n_projections)
    theta = checked_theta(src, index, o.theta_units)
    pixel = _pixel_size(o, src)
    phase = _phase_settings(o, src, pixel)
    steps = []
    report = {"raw": str(src.path), "raw_kind": src.kind, "raw_shape": [src.n_projections, *src.det_shape],
              "flats": src.n_flats, "darks": src.n_darks, "metadata": src.metadata, "options": o.as_dict(),
              "steps": steps}
    steps.append({"step": "select", "rows": list(rows), "cols": list(cols), "projections": int(index.size),
                  "first": int(index[0]), "last": int(index[-1]), "step_size": int(o.projections[2]),
                  "theta_first_deg": float(theta[0]), "theta_last_deg": float(theta[-1])})

    fm = flat_model(src, rows, cols, mode=o.flat, no_flat=o.no_flat, flats_before=o.flats_before,
                    repair=o.repair_pixels, n_projections=src.n_projections)
    steps.append({"step": "flat_dark", "mode": fm.mode, "flat_groups": int(fm.flats.shape[0]),
                  "bad_pixels": int(fm.bad.sum()), "min_transmission": o.min_transmission})

    ncols = cols[1] - cols[0]
    axis, how = _axis(o, src, fm, rows, cols, index, theta, pixel, phase)
    steps.append({"step": "center", "method": how, "axis_column_raw": None if axis is None else axis + cols[0]})
    c_lo, width = 0, ncols
    if axis is not None and o.crop_to_axis:
        half = min(axis + 0.5, ncols - 0.5 - axis)
        width = int(np.floor(2 * half)) // o.bin * o.bin
        if width < 8 * o.bin:
            raise ValueError(f"the rotation axis (column {axis + cols[0]:.1f}) is at the edge of the ROI; "
                             f"widen the ROI or pass --no-crop-to-axis")
        c_lo = int(round(axis + 0.5 - width / 2))
        steps.append({"step": "crop_to_axis", "cols": [cols[0] + c_lo, cols[0] + c_lo + width]})
    fm = fm.crop(slice(None), slice(c_lo, c_lo + width))
    read_cols = (cols[0] + c_lo, cols[0] + c_lo + width)
    nrows = rows[1] - rows[0]
    k = o.bin
    margin = _phase_margin(o, src, fm, rows, read_cols, index, pixel, phase, width, steps)
    per = max(1, int(o.slab_mb * 1e6 // (nrows * width * 4 * 6)))  # projections a slab: it and its working copies
    gains = _double_flat(o, src, fm, rows, read_cols, index, per, phase_margin=margin, steps=steps,
                         progress=progress)
    out_rows, out_cols = max(1, nrows // k), (width - 2 * margin) // k
    two_d = out_rows == 1
    axis_out = None if axis is None else (axis - c_lo - margin + 0.5) / k - 0.5
    geometry = scan_geometry(theta, pixel_size=(pixel[0] * k, pixel[1] * k), cols=out_cols,
                             rows=None if two_d else out_rows, axis_column=axis_out,
                             source_origin=o.source_origin, origin_detector=o.origin_detector)
    if phase:
        steps.append({"step": "phase_retrieval", "method": "paganin", **phase})
    steps.append({"step": "bin", "factor": k, "output_shape": list(geometry.shape),
                  "pixel_size_mm": [pixel[0] * k, pixel[1] * k]})

    bg_mode = o.background
    with atomic_path(out) as tmp:
        with h5py.File(tmp, "w") as f:
            chunks = (min(index.size, 16), out_cols) if two_d else (min(index.size, 16), min(out_rows, 8), out_cols)
            data_ds, bg_ds = create_scan_datasets(f, geometry, theta, background=bg_mode != "none", chunks=chunks)
            with _bar(index.size, "pass 1: flats, phase, -log", progress) as bar:
                for a, b, idx, counts in _read_slabs(src, index, per, rows, read_cols, o.projections[2]):
                    p = _line_integrals(counts, idx, fm, o, pixel, phase, gains)
                    p = _bin(p[..., margin:p.shape[-1] - margin], k)
                    data_ds[a:b] = p[:, 0] if two_d else p
                    bar.update(b - a)
            steps.append({"step": "minus_log", "slab_projections": per})
            _pass2(f, data_ds, bg_ds, geometry, o, steps, progress)
            contrast = _contrast(data_ds, bg_ds, geometry, o, steps)
            report["seconds"] = round(time.time() - t_start, 3)
            text = json.dumps(report, indent=2, default=_jsonable)
            set_scan_attrs(f, contrast, {"prepared_by": "bubsub prepare", "prepare_report": text})
    atomic_write_text(out.with_name(out.name + ".report.json"), text)
    return report


def _jsonable(v):
    if isinstance(v, Path):
        return str(v)
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(type(v).__name__)


#: Raw pixels about the searches' axis within which ``--center auto`` refines it (:func:`center_sharpness`).
SHARPEN_WIDTH = 2.0
#: Raw pixels about the sharpest FBP's coarse column within which ``--center auto`` refines it on a row with no
#: air at its sides (:func:`_axis_without_air`; the coarse column within 0.33 raw pixels of the axis on the scans
#: of ``python -m bubsub.bench fov --local-axis``, seeds 0-59).
LOCAL_SHARPEN_WIDTH = 2.0
#: Raw pixels within which the seam search must confirm the sharpest FBP's coarse column on a row with no air at
#: its sides (the seam up to 1.55 raw pixels off on those scans).
SEAM_AGREE = 3.0
#: Phase-retrieval lengths cropped from each side of a scan with no air at its sides (see :func:`_phase_margin`).
PHASE_MARGIN_LENGTHS = 2.0


def _phase_margin(o, src, fm, rows, read_cols, index, pixel, phase, width, steps):
    """Raw columns to drop at each side after phase retrieval when the sample is wider than the detector.

    Paganin's filter (:func:`paganin_filter`) recovers the thickness at a
    column from the intensity within a few of its lengths
    ``sqrt(delta_beta * distance * wavelength / (4 pi))`` around it. Beside
    air that intensity is known (the padding continues the air); a sample
    wider than the detector continues beyond it with what the detector does
    not see, so the outermost columns come out wrong by up to the size of
    the phase-contrast fringes (a tenth in ``-log`` at 16 keV, 300 mm). They
    are cropped: :data:`PHASE_MARGIN_LENGTHS` lengths at each side, rounded
    up to whole binned pixels, when the middle row has no air at its sides
    (:func:`sees_air`). Zero without phase retrieval or when air is there.
    """
    if not phase:
        return 0
    r = (rows[0] + rows[1]) // 2
    row_fm = fm.crop(slice(r - rows[0], r - rows[0] + 1), slice(None))
    sub = index[:: max(1, index.size // 64)]
    sino = np.stack([_line_integrals(src.read("data", slice(int(i), int(i) + 1), (r, r + 1), read_cols),
                                     np.array([i]), row_fm, o, None, None)[0, 0] for i in sub])
    if sees_air(sino):
        return 0
    length = np.sqrt(phase["delta_beta"] * phase["distance_mm"] * wavelength_mm(phase["energy_kev"]) / (4 * np.pi))
    k = o.bin
    margin = int(np.ceil(PHASE_MARGIN_LENGTHS * length / pixel[1] / k)) * k
    if width - 2 * margin < 8 * k:
        raise ValueError(f"the detector ({width} columns) is too narrow for phase retrieval of a sample wider than "
                         f"it: {margin} columns at each side are within two phase-retrieval lengths of its edge")
    steps.append({"step": "phase_margin", "cols_each_side": margin, "phase_length_mm": float(length),
                  "why": "no air at the detector's sides: the outermost columns' phase retrieval lacks the "
                         "intensity beyond the detector"})
    return margin


def _pixel_size(o, src):
    if o.pixel_size is not None:
        return (o.pixel_size, o.pixel_size)
    px, py = src.metadata.get("pixel_size_x_mm"), src.metadata.get("pixel_size_y_mm")
    if px is None and py is None:
        raise ValueError(f"{src.path.name} states no detector pixel size; pass --pixel-size (e.g. 3um)")
    return (py or px, px or py)


def _phase_settings(o, src, pixel):
    if o.delta_beta is None:
        return None
    energy = o.energy or src.metadata.get("energy_kev")
    distance = o.distance or src.metadata.get("distance_mm")
    missing = [n for n, v in (("--energy", energy), ("--distance", distance)) if v is None]
    if missing:
        raise ValueError(f"phase retrieval (--delta-beta) needs {' and '.join(missing)}; {src.path.name} does not "
                         f"state them")
    return {"delta_beta": o.delta_beta, "energy_kev": energy, "distance_mm": distance,
            "pixel_size_mm": list(pixel), "padding": "edge, 2x, fast FFT length"}


def _read_slabs(src, index, per, rows, cols, step):
    """The raw projections ``index`` in slabs of ``per``: ``(a, b, index[a:b], counts)`` for each."""
    for a, b in _slabs(index.size, per):
        idx = index[a:b]
        yield a, b, idx, src.read("data", slice(int(idx[0]), int(idx[-1]) + 1, step), rows, cols)


def _transmission(counts, idx, fm):
    """Flat- and dark-corrected transmission of ``counts``, its bad pixels repaired."""
    t, _ = fm.transmission(counts, idx)
    if fm.bad.any():
        repair_pixels(t, fm.bad)
    return t


def _double_flat(o, src, fm, rows, read_cols, index, per, *, phase_margin, steps, progress):
    """The pixel gains that the flats do not show (:func:`~bubsub.core.prep.gains.stripe_gains`), from a pass
    over all projections, where ``o.double_flat`` asks for them: ``"on"``, or ``"auto"`` on a sample wider than
    the detector with phase retrieval (``phase_margin`` > 0). Its reconstruction takes what is the same in every
    view as a detector term, which a gain error is no longer once phase retrieval has spread it
    (:mod:`bubsub.core.prep.gains`). None otherwise."""
    if o.double_flat == "off" or (o.double_flat == "auto" and phase_margin == 0):
        return None
    total = 0.0
    with _bar(index.size, "pixel gains (double flat-field)", progress) as bar:
        for a, b, idx, counts in _read_slabs(src, index, per, rows, read_cols, o.projections[2]):
            t = _transmission(counts, idx, fm)
            total = total + np.log(np.clip(t, o.min_transmission, None)).sum(axis=0)
            bar.update(b - a)
    gains = stripe_gains(total / index.size)
    log_gains = np.log(gains.astype(np.float64))
    steps.append({"step": "double_flat_field", "median_columns": GAIN_MEDIAN_COLUMNS,
                  "log_gain_rms": float(np.sqrt(np.mean(log_gains ** 2))),
                  "log_gain_largest": float(np.max(np.abs(log_gains))),
                  "why": "pixel gains the flats do not show, divided out before phase retrieval, which would "
                         "spread them differently in each view" if o.double_flat == "auto" else "asked for"})
    return gains


def _line_integrals(counts, idx, fm, o, pixel, phase, gains=None):
    t = _transmission(counts, idx, fm)
    if gains is not None:
        t /= gains
    if phase:
        t = paganin_filter(t, pixel_size=pixel, energy=phase["energy_kev"], distance=phase["distance_mm"],
                           delta_beta=phase["delta_beta"])
    return minus_log(t, o.min_transmission)


def _bin(p, k):
    if k == 1:
        return p
    n, r, c = p.shape
    if r == 1:
        return p.reshape(n, 1, c // k, k).mean(axis=3)
    return p.reshape(n, r // k, k, c // k, k).mean(axis=(2, 4))


def _axis(o, src, fm, rows, cols, index, theta, pixel=None, phase=None):
    """Axis column in ROI coordinates (None: the ROI centre is taken as is) and how it was found.

    ``auto``: Vo's method on the middle row, and where Vo's column stands
    more than :data:`CENTRE_AGREE` pixels from both the seam search
    (:func:`center_seam`) and the symmetry of the mean projection
    (:func:`center_symmetry`) while these two agree within it, their mean;
    where that row has no air at the detector's sides (:func:`sees_air`: a
    sample wider than the detector) the sharpest FBP over the detector's
    middle checked by the seam instead (:func:`_axis_without_air`). All but
    Vo's run on the phase-retrieved row when ``--delta-beta`` is given
    (phase-contrast fringes would dominate them). The column found is then
    refined by the least total variation of the row's FBP
    (:func:`center_sharpness`), on the same row: beside air within
    :data:`SHARPEN_WIDTH` pixels, without air within
    :data:`LOCAL_SHARPEN_WIDTH` pixels with the row continued by its edge
    columns.
    """
    if isinstance(o.center, float):
        c = o.center - cols[0]
        if not 0 <= c <= cols[1] - cols[0] - 1:
            raise ValueError(f"--center {o.center} is outside the ROI columns {cols[0]}:{cols[1]}")
        return c, "given"
    if o.center == "none":
        return None, "none (detector centre)"
    method = "vo" if o.center == "auto" else o.center
    mean_fm = fm if fm.mode != "best" else fm.__class__("mean", fm.dark, fm.flats.mean(0)[None], fm.times[:1],
                                                        fm.bad)
    if method == "pair":
        i, j, err = closest_pair(theta)
        step = float(np.median(np.abs(np.diff(theta))))
        if err > 0.5 * step + 1e-9:
            raise ValueError(f"no two projections are 180 degrees apart (closest {180 + err:.3g}); use --center vo "
                             f"or give the axis column")
        pa = [_line_integrals(src.read("data", slice(int(index[m]), int(index[m]) + 1), rows, cols),
                              index[m:m + 1], mean_fm, o, None, None)[0] for m in (i, j)]
        return center_pair(pa[0], pa[1]), f"pair (projections {int(index[i])}, {int(index[j])})"
    r = (rows[0] + rows[1]) // 2
    in180 = np.abs(theta - theta[0]) < 180.0 - 1e-6
    sub = index[in180]
    row_fm = mean_fm.crop(slice(r - rows[0], r - rows[0] + 1), slice(None))
    sino = np.concatenate([
        _line_integrals(src.read("data", slice(int(sub[a]), int(sub[b - 1]) + 1, o.projections[2]), (r, r + 1),
                                 cols), sub[a:b], row_fm, o, None, None)[:, 0]
        for a, b in _slabs(sub.size, 256)])
    if o.center != "auto":
        return center_vo(sino), f"vo (row {r}, {sub.size} projections)"
    smooth = sino
    if phase:
        smooth = np.concatenate([
            _line_integrals(src.read("data", slice(int(sub[a]), int(sub[b - 1]) + 1, o.projections[2]), (r, r + 1),
                                     cols), sub[a:b], row_fm, o, pixel, phase)[:, 0] for a, b in _slabs(sub.size, 256)])
    where = f"row {r}, {sub.size} projections"
    if not sees_air(sino):
        return _axis_without_air(smooth, theta[in180], phase, pixel, where, cols[0])
    return _sharpened(smooth, theta[in180], *_axis_beside_air(sino, smooth, theta[in180], where))


def _axis_beside_air(sino, smooth, theta, where):
    """Vo's column, or the seam and symmetry searches' mean where they agree and Vo's stands apart."""
    vo = center_vo(sino)
    try:
        seam = center_seam(smooth, theta)
    except ValueError:  # not an even 180-degree scan
        return vo, f"vo ({where})"
    sym = center_symmetry(smooth)
    if abs(seam - sym) <= CENTRE_AGREE < min(abs(vo - seam), abs(vo - sym)):
        return 0.5 * (seam + sym), (f"seam and symmetry ({where}; Vo's method gave column {vo:.2f}, "
                                    f"{abs(vo - seam):.1f} pixels away)")
    return vo, f"vo ({where})"


def _sharpened(sino, theta, c, method, width=SHARPEN_WIDTH, truncated=False):
    """``c`` refined by :func:`center_sharpness` within ``width`` on the (phase-retrieved) row: ``(column, method)``."""
    sharp = center_sharpness(sino, theta, c, width=width, truncated=truncated)
    if abs(sharp - c) >= width - 0.25:  # the least at the window's edge: no refinement found
        return c, method
    return sharp, f"{method}, refined by the least total variation of its FBP ({sharp - c:+.2f} pixels)"


def _axis_without_air(sino, theta, phase, pixel, where, first_col=0):
    """The axis of a row with no air at its sides: the sharpest FBP, where the seam search agrees.

    Both searches see the interior only: with phase retrieval, the columns
    within :data:`PHASE_MARGIN_LENGTHS` phase-retrieval lengths of the
    detector's sides are left out (:func:`_phase_margin`). The least total
    variation of the FBP of the interior columns continued by their edge
    columns (:func:`center_sharpest`, coarse, over the detector's middle)
    and the seam of the 180-degree sinogram (:func:`center_seam`) are two
    independent criteria. Where the seam's least lies within
    :data:`SEAM_AGREE` of the sharpest column, or its cost has a local
    least there (the seam compares two rows at each end of the 180 degrees,
    where the outer bubbles move several pixels between projections, and
    its least can lie elsewhere: 43 and 61 pixels off on two of the scans
    of ``python -m bubsub.bench fov --local-axis``, seeds 0-59), the
    sharpest column is refined within :data:`LOCAL_SHARPEN_WIDTH`
    (:func:`center_sharpness` with ``truncated``, at full resolution).
    Otherwise no axis is guessed (the sharpest FBP of a row with little
    foam in it can settle pixels off): the error asks for ``--center``. A
    scan that is not an even 180-degree scan has no seam: the sharpest
    column is taken, with a warning, where it is distinct (the next local
    least more than :data:`SHARPEST_MARGIN` of it above it).
    """
    m = 0
    if phase:
        length = np.sqrt(phase["delta_beta"] * phase["distance_mm"] * wavelength_mm(phase["energy_kev"]) / (4 * np.pi))
        m = min(int(np.ceil(PHASE_MARGIN_LENGTHS * length / pixel[1])), sino.shape[1] // 4)
    inner = sino[:, m:sino.shape[1] - m]
    sharpest, margin = center_sharpest(inner, theta, truncated=True)
    at = f"detector column {sharpest + m + first_col:.1f}"
    stop = (f"the rotation axis of this sample, wider than the detector (no air at its sides), could not be found "
            f"reliably: the sharpest filtered back-projection ({where}) is at {at}")
    ask = "give the axis with --center COLUMN (raw detector column)"
    method = f"sharpest FBP over the detector's middle ({where}; no air at the detector's sides"
    try:
        seam = center_seam(inner, theta)
    except ValueError:  # not an even 180-degree scan: the sharpest column alone
        if margin < SHARPEST_MARGIN:
            raise ValueError(f"{stop} but hardly sharper than at other columns, and this is not an even 180-degree "
                             f"scan (no seam search to check it); {ask}") from None
        warnings.warn(f"the axis of this sample, wider than the detector, is taken at {at} (the sharpest filtered "
                      f"back-projection), unchecked: not an even 180-degree scan, no seam search; check the "
                      f"reconstruction or give --center", stacklevel=2)
        method += "; unchecked: no seam search)"
    else:
        cols, w = inner.shape[1] - 1, SEAM_AGREE
        if abs(seam - sharpest) <= w:
            method += f"), checked by the seam of the 180-degree sinogram ({seam - sharpest:+.2f} pixels from it)"
        else:
            near = center_seam(inner, theta, search=((sharpest - w) / cols, (sharpest + w) / cols))
            if abs(near - sharpest) >= w - 0.25:  # the seam's cost falls all the way to the window's edge
                raise ValueError(f"{stop}, the seam of the 180-degree sinogram at detector column "
                                 f"{seam + m + first_col:.1f}; {ask}")
            method += (f"), checked by a local least of the seam's cost ({near - sharpest:+.2f} pixels from it; its "
                       f"least at column {seam + m + first_col:.1f})")
    sharp, method = _sharpened(inner, theta, sharpest, method, width=LOCAL_SHARPEN_WIDTH, truncated=True)
    return sharp + m, method


#: How much sharper than any other local least the least total variation over the detector's middle must be
#: (:func:`center_sharpest`'s ``margin``) for ``--center auto`` to take it unchecked on a row with no air at its
#: sides of a scan that is not an even 180-degree scan: half the least margin on the foams of ``python -m
#: bubsub.bench fov --local-axis`` (0.010-0.036, seeds 0-59).
SHARPEST_MARGIN = 0.005
#: Pixels within which the seam and symmetry centres must agree with each other, and beyond which Vo's must
#: stand from both, for ``--center auto`` to take their mean instead of Vo's.
CENTRE_AGREE = 2.0


def _pass2(f, data_ds, bg_ds, geometry, o, steps, progress):
    two_d = geometry.ndim == 2
    n = geometry.n_angles
    out_rows = 1 if two_d else geometry.det_rows
    cols = geometry.det_cols
    per = max(1, int(o.slab_mb * 1e6 // (n * cols * 4 * 6)))
    mode = o.background
    file_bg = _background_file(o.background, geometry) if isinstance(mode, Path) else None
    row_geom = geometry if two_d else None
    liquids, drift, offsets, chords = [], [], [], []
    with _bar(out_rows, "pass 2: stripes, background", progress) as bar:
        for a, b in _slabs(out_rows, per):
            block = data_ds[()][:, None] if two_d else data_ds[:, a:b]
            if o.stripes != "none":
                for r in range(block.shape[1]):
                    block[:, r] = remove_stripes(block[:, r], o.stripes)
                _store(data_ds, block, a, b, two_d)
            if bg_ds is not None:
                stored = True  # the data as stored; False once a row is corrected here
                if file_bg is not None:
                    bg = file_bg[:, None] if two_d else file_bg[:, a:b]
                elif mode in ("reproject", "auto"):
                    if row_geom is None:
                        row_geom = _row_geometry(geometry)
                    bg = np.empty_like(block)
                    for r in range(block.shape[1]):
                        if mode == "auto" and not sees_air(block[:, r]):
                            bg[:, r], fit = chord_background(block[:, r], row_geom, radius=o.liquid_radius)
                            beyond = foam_beyond(fit, row_geom)  # the foam the reconstruction leaves unmodelled
                            bg[:, r] += beyond
                            fit["foam_beyond_at_axis"] = float(beyond[np.argmin(np.abs(detector_offsets(row_geom)))])
                            fit["drift_range"] = drift_offsets(block[:, r], bg[:, r])
                            chords.append(fit)
                            stored = False
                        elif mode == "auto":
                            bg[:, r] = radial_background(block[:, r], row_geom)[None]
                        else:
                            bg[:, r], lq, _ = reproject_background(block[:, r], row_geom, o.foam_radius)
                            liquids.append(lq)
                else:
                    env = envelope_background(block)
                    half = n // 2
                    drift.append(float(np.median(np.abs(envelope_background(block[:half]) -
                                                        envelope_background(block[half:])))))
                    bg = np.broadcast_to(env[None], block.shape)
                if air_offsets(block, bg, offsets) or not stored:
                    _store(data_ds, block, a, b, two_d)
                _store(bg_ds, bg, a, b, two_d)
            bar.update(b - a)
    if o.stripes != "none":
        steps.append({"step": "stripes", "method": o.stripes, "library": "algotom"})
    if bg_ds is not None:
        entry = {"step": "background", "method": str(mode) if not isinstance(mode, str) else
                 ("radial (ring medians of an FBP, reprojected; where a row has no air at its sides, the liquid "
                  "cylinder's chord profile)" if mode == "auto" else mode)}
        if chords:
            entry["wider_than_detector"] = {
                "rows": len(chords), "method": "liquid cylinder's chord profile fitted (chord_background)" + (
                    ", its radius given (--liquid-radius)" if o.liquid_radius else "") + (
                    f", with the mean projection of the foam beyond {backgrounds.FOAM_BEYOND_REACH} field-of-view "
                    "radii (foam_beyond)"),
                **{k: float(np.median([c[k] for c in chords])) for k in chords[0]}}
        if liquids:
            entry["liquid_attenuation_per_mm"] = float(np.median(liquids))
            entry["foam_radius_mm"] = o.foam_radius
        if drift:
            entry["halves_median_difference"] = float(np.median(drift))
            entry["noise"] = noise_level(data_ds[: min(n, 32)])
        entry["air_offset"] = {
            "rows_corrected": len(offsets), "rows": out_rows,
            "median_abs_offset": float(np.median(np.abs(np.concatenate(offsets)))) if offsets else 0.0,
            "method": "each projection's median of data - background over the air columns subtracted (air_offsets)"}
        steps.append(entry)


def _store(ds, block, a, b, two_d):
    if two_d:
        ds[...] = block[:, 0]
    else:
        ds[:, a:b] = block


def _row_geometry(geometry):
    """The 2D geometry of one detector row of a parallel 3D geometry (same angles and axis)."""
    if geometry.ndim == 2:
        return geometry
    if geometry.is_cone:
        raise ValueError("--background auto and reproject support parallel beams only; use envelope or a file")
    return row_geometry(geometry)


def _background_file(path, geometry):
    try:
        with h5py.File(path, "r") as f:
            name = "exchange/background" if "exchange/background" in f else "exchange/data"
            bg = np.asarray(f[name][()], dtype=np.float32)
    except OSError as exc:
        raise ValueError(f"--background {path}: not a readable HDF5 file ({exc})") from None
    if bg.shape != geometry.shape and bg.shape != geometry.shape[1:]:
        raise ValueError(f"--background {path}: '/{name}' has shape {bg.shape}; the prepared scan is "
                         f"{geometry.shape} (or one projection {geometry.shape[1:]})")
    if not np.all(np.isfinite(bg)):
        raise ValueError(f"--background {path}: '/{name}' contains NaN or inf")
    return np.broadcast_to(bg, geometry.shape)


def _contrast(data_ds, bg_ds, geometry, o, steps):
    """The bubble contrast (given or estimated from the middle slice), its sign checked against the data."""
    two_d = geometry.ndim == 2
    mid = None if two_d else geometry.det_rows // 2
    sino = data_ds[()] if two_d else data_ds[:, mid]
    entry = {"step": "contrast"}
    if o.contrast is not None:
        contrast = o.contrast
        entry["source"] = "given"
    else:
        g2 = _row_geometry(geometry)
        row = sino
        if bg_ds is not None and not sees_air(sino):  # local tomography: the liquid's chords out (no cupping)
            row = sino - (bg_ds[()] if two_d else bg_ds[:, mid])
        liquid, gas = row_phases(row, g2, o.foam_radius)
        contrast = gas - liquid
        entry.update(source="estimated from an FBP of the middle row (Otsu split of the foam region)",
                     liquid_per_mm=liquid, gas_per_mm=gas)
        if contrast == 0:
            raise ValueError("could not estimate the bubble contrast (gas and liquid look alike); pass --contrast")
    entry["bubble_contrast_per_mm"] = float(contrast)
    if bg_ds is not None:
        bd = sino - (bg_ds[()] if two_d else bg_ds[:, mid])
        noise = 3 * noise_level(bd)
        pos, neg = signal_masses(bd, noise)
        entry["sign_check"] = {"positive_mass": pos, "negative_mass": neg}
        problem = contrast_sign_error(contrast, bd, noise=noise)
        if problem:
            raise ValueError(f"{problem}; pass --contrast with the other sign, or check the background")
    else:
        entry["sign_check"] = "not possible without a background"
    steps.append(entry)
    return contrast
