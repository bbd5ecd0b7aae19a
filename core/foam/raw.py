"""Realistic raw synchrotron scans of a 2D foam: counts, flats and darks as a beamline writes them.

The sample: a liquid column in a cylindrical container (wall of another
material), centred on the rotation axis, holding the bubbles of a 2D foam
phantom; it is invariant along the axis, so every detector row sees the same
object. Per projection angle:

1. exact chord lengths on a detector :func:`wave_supersampling` times
   finer than the real one (bubbles: the phantom's polygons through
   :class:`~bubsub.core.projection.projector.MeshProjector`; liquid and
   wall: analytic discs), the axis off the detector centre by ``axis_offset``
   pixels;
2. the complex transmission ``exp(-mu t / 2 - i k delta t)`` of each
   material, Fresnel-propagated over ``distance`` at ``energy``
   (:func:`bubsub.core.prep.phase.fresnel_propagate`), intensity integrated
   over each real pixel. The wave is sampled at ``wave_pixel`` or finer:
   at a bubble's edge the phase ``k delta t`` turns steeply (the chord's
   slope is unbounded there), and a coarser sampling aliases it, so that
   the propagated intensity lacks most of the phase contrast that
   single-distance phase retrieval then divides out: the retrieved line
   integrals come out blurred by the Paganin length (on the local
   tomography case of ``python -m bubsub.bench fov``, 12 um pixels at 16
   keV and 300 mm, the retrieved bubbles' signal keeps 0.20 of its
   amplitude at 0.08 cycles per pixel when sampled at 6 um, 0.61 at 3 um,
   1.01 at 1.5 um and 1.10 at 0.75 um);
3. the beam: a flat field with a smooth pattern that decays in intensity
   and drifts vertically during the scan (flats are taken before and after
   it), darks with read noise, fixed-pattern column gain errors that the
   flats do not show (stripes, ring artefacts), dead and hot pixels,
   Poisson counting noise, 16-bit saturation.

Written as a Data Exchange raw file (``/exchange/data|data_white|data_dark``
uint16, ``/exchange/theta`` degrees, instrument metadata with units).

A container wider than the detector (local, or interior, tomography) is
allowed with ``wider_than_detector=True``: the wave (liquid and bubbles) is
then computed and propagated over the whole container's width and the
detector crops it, as at a beamline.
:func:`disc_foam` fills a liquid cylinder with bubbles out to its wall and
:func:`write_raw_simulation` writes a simulation folder (``raw.h5``,
``truth.json``, ``phantom.json``) that ``bubsub evaluate`` scores against.
"""

from __future__ import annotations

import dataclasses

import h5py
import numpy as np

from bubsub.core.io.atomic import atomic_path, atomic_write_text
from bubsub.core.prep.phase import fresnel_propagate, wavelength_mm
from bubsub.core.foam.phantoms import foam2d
from bubsub.core.io.meshio import write_polygons_json
from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.projection.projector import MeshProjector

__all__ = ["RawSettings", "raw_settings", "wave_supersampling", "simulate_raw", "write_raw", "disc_foam",
           "write_raw_simulation"]


@dataclasses.dataclass(frozen=True)
class RawSettings:
    """A raw scan's acquisition (lengths mm, energy keV, attenuation 1/mm)."""

    n_angles: int = 180
    rows: int = 8
    cols: int = 800
    pixel_size: float = 0.012
    axis_offset: float = 13.3  # pixels right of the detector centre
    energy: float = 16.0
    distance: float = 250.0
    photons: float = 2e4
    dark_level: float = 100.0
    read_noise: float = 3.0
    container_radius: float = 4.0  # inner radius of the wall
    wall: float = 0.3
    liquid_mu: float = 0.1
    liquid_delta: float = 9.0e-7
    wall_mu: float = 0.08
    wall_delta: float = 1.05e-6
    n_flats: int = 20  # half before, half after the scan
    n_darks: int = 10
    decay: float = 0.15  # fractional beam intensity loss over the scan
    drift_rows: float = 1.5  # vertical drift of the flat pattern over the scan, rows
    stripe_columns: int = 6
    stripe_gain: float = 0.03
    dead_pixels: int = 12
    hot_pixels: int = 6
    supersample: int = 4  # fine samples per pixel, at least (see wave_pixel)
    wave_pixel: float = 0.0015  # the wave's sampling, mm, at most (see wave_supersampling)
    seed: int = 0
    wider_than_detector: bool = False  # allow a container the detector does not see whole

    def __repr__(self):
        fields = ", ".join(f"{f.name}={getattr(self, f.name)!r}" for f in dataclasses.fields(self)
                           if getattr(self, f.name) != f.default)
        return f"raw_settings({fields})"

    @property
    def axis_column(self):
        """Detector column (pixel index) the rotation axis projects to."""
        return self.cols / 2 - 0.5 + self.axis_offset

    @property
    def delta_beta(self):
        """``delta / beta`` of the liquid (the single material for phase retrieval)."""
        beta = self.liquid_mu * wavelength_mm(self.energy) / (4 * np.pi)
        return self.liquid_delta / beta


def wave_supersampling(settings):
    """Fine samples of the wave per detector pixel: ``supersample`` or more, so that their pitch is at most ``wave_pixel``.

    Parameters
    ----------
    settings : RawSettings

    Returns
    -------
    int
        ``max(supersample, ceil(pixel_size / wave_pixel))``.
    """
    return max(int(settings.supersample), int(np.ceil(settings.pixel_size / settings.wave_pixel - 1e-9)))


def raw_settings(**kw):
    """Validated :class:`RawSettings`."""
    s = RawSettings(**kw)
    for name in ("n_angles", "rows", "cols", "supersample"):
        v = getattr(s, name)
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ValueError(f"{name} must be a positive integer, got {v!r}")
    for name in ("pixel_size", "energy", "distance", "photons", "container_radius", "wave_pixel"):
        if not getattr(s, name) > 0:
            raise ValueError(f"{name} must be positive, got {getattr(s, name)!r}")
    half = 0.5 * s.cols * s.pixel_size - abs(s.axis_offset) * s.pixel_size
    if s.container_radius + s.wall >= half and not s.wider_than_detector:
        raise ValueError(f"the container (outer radius {s.container_radius + s.wall} mm) does not fit in the "
                         f"{half:.3g} mm the detector sees on each side of the axis; pass "
                         f"wider_than_detector=True for a local-tomography scan")
    return s


def _chord(radius, s):
    return 2.0 * np.sqrt(np.maximum(radius * radius - s * s, 0.0))


def simulate_raw(phantom, settings):
    """Raw counts of a 2D foam phantom in the settings' container.

    Parameters
    ----------
    phantom : FoamPhantom
        2D; its bubbles must lie inside ``container_radius``.
    settings : RawSettings

    Returns
    -------
    dict
        ``data`` (n_angles, rows, cols) uint16, ``data_white`` and
        ``data_dark`` (n, rows, cols) uint16, ``theta`` (n_angles,) degrees.
    """
    s = settings
    if phantom.ndim != 2:
        raise ValueError("simulate_raw needs a 2D foam phantom")
    reach = max(float(np.max(np.hypot(*b.vertices.T))) for b in phantom.bubbles) if phantom.bubbles else 0.0
    if reach >= s.container_radius:
        raise ValueError(f"bubbles reach {reach:.3g} mm from the axis, outside the container ({s.container_radius} mm)")
    rng = np.random.default_rng(s.seed)
    theta = np.linspace(0.0, 180.0, s.n_angles, endpoint=False)
    ss = wave_supersampling(s)
    fine_cols, fine_px = s.cols * ss, s.pixel_size / ss
    # a container wider than the detector: the wave is computed (bubbles and all) over its whole width, so that
    # the propagation to the detector's outermost columns is that of the whole sample, and the detector crops it
    extra = 0
    if s.wider_than_detector:
        half = 0.5 * s.cols * s.pixel_size + abs(s.axis_offset) * s.pixel_size
        extra = int(np.ceil(max(s.container_radius + s.wall - half, 0.0) / fine_px)) + 4 * ss
    wide = fine_cols + 2 * extra
    # signed distance of each fine sample from the axis, mm
    u = ((np.arange(-extra, fine_cols + extra) + 0.5) / ss - 0.5 - s.axis_column) * s.pixel_size
    geom = ScanGeometry.parallel(np.radians(theta), pixel_size=fine_px, cols=wide)
    vec = np.array(geom.vectors)
    shift = fine_cols / 2 - 0.5 - (s.axis_column + 0.5) * ss + 0.5
    vec[:, 2:4] += shift * vec[:, 4:6]
    geom = ScanGeometry.from_astra("parallel_vec", vec, det_count=wide)
    gas = MeshProjector(geom).forward(list(phantom.bubbles)) / phantom.contrast  # chord through gas, mm
    inner, outer = _chord(s.container_radius, u), _chord(s.container_radius + s.wall, u)
    liquid = np.maximum(inner[None] - gas, 0.0)
    wall = (outer - inner)[None]
    k = 2 * np.pi / wavelength_mm(s.energy)
    field = np.exp(-0.5 * (s.liquid_mu * liquid + s.wall_mu * wall)
                   - 1j * k * (s.liquid_delta * liquid + s.wall_delta * wall))
    pad = fine_cols // 2
    intensity = np.empty((s.n_angles, s.cols))
    for i, f in enumerate(field):
        fz = fresnel_propagate(np.pad(f, pad, mode="edge"), pixel_size=fine_px, energy=s.energy,
                               distance=s.distance)[pad + extra:pad + extra + fine_cols]
        intensity[i] = (np.abs(fz) ** 2).reshape(s.cols, ss).mean(axis=1)
    return _detector(intensity, theta, s, rng)


def _flat_pattern(s, rng):
    rows, cols = np.arange(s.rows)[:, None], np.arange(s.cols)[None, :]
    phase = rng.uniform(0, 2 * np.pi, 3)

    def pattern(row_shift):
        r = rows + row_shift
        return (1.0 + 0.15 * np.sin(2 * np.pi * r / 23.0 + phase[0])
                + 0.08 * np.sin(2 * np.pi * cols / 97.0 + phase[1]) * np.cos(2 * np.pi * r / 17.0 + phase[2])
                + 0.05 * np.cos(2 * np.pi * cols / 411.0))
    return pattern


def _detector(intensity, theta, s, rng):
    n = s.n_angles
    pattern = _flat_pattern(s, rng)
    nb = s.n_flats // 2
    total = n + s.n_flats  # acquisition time in frames: flats before, projections, flats after

    def beam(t):
        frac = t / total
        return s.photons * (1 - s.decay * frac) * pattern(s.drift_rows * frac)

    gain = np.ones(s.cols)
    cols = rng.choice(s.cols, size=s.stripe_columns, replace=False)
    gain[cols] += rng.choice([-1, 1], size=cols.size) * s.stripe_gain * rng.uniform(0.5, 1.0, cols.size)
    dead = rng.choice(s.rows * s.cols, size=s.dead_pixels, replace=False)
    hot = rng.choice(s.rows * s.cols, size=s.hot_pixels, replace=False)

    def counts(mean, with_beam):
        c = rng.poisson(np.maximum(mean, 0)).astype(np.float64) if with_beam else np.zeros_like(mean)
        c += s.dark_level + rng.normal(0.0, s.read_noise, c.shape)
        flat = c.reshape(c.shape[0], -1)
        flat[:, dead] = 0.0 if with_beam else s.dark_level
        flat[:, hot] = 60000.0
        return np.clip(np.rint(c), 0, 65535).astype(np.uint16)

    before = np.stack([beam(i) for i in range(nb)])
    after = np.stack([beam(nb + n + i) for i in range(s.n_flats - nb)])
    proj = np.stack([beam(nb + i) * intensity[i][None, :] * gain[None, :] for i in range(n)])
    return {
        "data": counts(proj, True),
        "data_white": counts(np.concatenate([before, after]), True),
        "data_dark": counts(np.zeros((s.n_darks, s.rows, s.cols)), False),
        "theta": theta,
    }


def write_raw(path, raw, settings):
    """Write a raw scan as a Data Exchange HDF5 file (atomically); returns the path."""
    s = settings
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            ex = f.create_group("exchange")
            for name in ("data", "data_white", "data_dark"):
                ex.create_dataset(name, data=raw[name], chunks=(1,) + raw[name].shape[1:])
            ex.create_dataset("theta", data=raw["theta"]).attrs["units"] = "degrees"
            inst = f.create_group("measurement/instrument")
            inst.create_dataset("monochromator/energy", data=s.energy).attrs["units"] = "keV"
            for axis in ("x", "y"):
                inst.create_dataset(f"detector/pixel_size_{axis}", data=s.pixel_size * 1e3).attrs["units"] = "um"
            inst.create_dataset("detection_system/distance", data=s.distance).attrs["units"] = "mm"
            f.attrs["simulated"] = 1
            f.attrs["axis_column"] = s.axis_column
            f.attrs["delta_beta"] = s.delta_beta
    return path


def disc_foam(seed, radius, *, n_bubbles, radius_range, liquid_attenuation=0.1, gap=0.02, margin=0.02,
              perturbation=0.03):
    """A 2D foam filling a disc: bubbles of :func:`bubsub.core.foam.phantoms.foam2d` inside ``radius``.

    The bubbles are placed in the disc's bounding square (random sequential
    addition) and those not wholly inside ``radius - margin`` are dropped,
    so the foam reaches the container's wall all round.

    Parameters
    ----------
    seed : int
    radius : float
        The liquid cylinder's radius, mm.
    n_bubbles : int
        Bubbles placed in the square (about ``pi / 4`` of them stay).
    radius_range : (2,) float
        Smallest and largest mean bubble radius, mm.
    liquid_attenuation, gap, margin, perturbation
        As for ``foam2d`` (mm, 1/mm).

    Returns
    -------
    FoamPhantom
        2D; its ``size`` is the disc's bounding square.
    """
    ph = foam2d(seed, n_bubbles=n_bubbles, size=2.0 * radius, radius_range=radius_range,
                liquid_attenuation=liquid_attenuation, gap=gap, margin=margin, perturbation=perturbation)
    keep = [k for k, b in enumerate(ph.bubbles) if np.hypot(*b.vertices.T).max() < radius - margin]
    if not keep:
        raise ValueError(f"no bubble fits inside the disc of radius {radius} mm; reduce radius_range")
    return dataclasses.replace(ph, bubbles=tuple(ph.bubbles[k] for k in keep),
                               centres=ph.centres[keep], radii=ph.radii[keep])


def write_raw_simulation(out, phantom, settings, *, grid=1000):
    """Simulate a raw scan of a 2D foam and write a simulation folder.

    Parameters
    ----------
    out : str or os.PathLike
        Folder (created): ``raw.h5`` (:func:`write_raw`), ``truth.json``
        (the bubbles' outlines) and ``phantom.json`` (what ``bubsub evaluate``
        reads: the truth grid of ``grid`` pixels across the phantom, the
        settings, the true axis column and ``delta_beta``).
    phantom : FoamPhantom
        2D.
    settings : RawSettings

    Returns
    -------
    pathlib.Path
        The raw file.
    """
    import json
    from pathlib import Path


    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_raw(out / "raw.h5", simulate_raw(phantom, settings), settings)
    write_polygons_json(out / "truth.json", phantom.bubbles)
    shape, extent = phantom.grid(grid)
    meta = {"phantom": "foam2d-raw", "ndim": 2, "seed": settings.seed, "size": list(phantom.size),
            "liquid_attenuation": phantom.liquid_attenuation, "bubble_contrast": phantom.contrast,
            "bubbles": len(phantom.bubbles), "grid_shape": list(shape), "grid_extent": list(extent),
            "angles": settings.n_angles, "photons": settings.photons, "beam": "parallel", "truth": "truth.json",
            "raw": dataclasses.asdict(settings), "axis_column": settings.axis_column,
            "delta_beta": settings.delta_beta}
    atomic_write_text(out / "phantom.json", json.dumps(meta, indent=2))
    return out / "raw.h5"
