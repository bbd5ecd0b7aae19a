"""A simulated synchrotron foam column: rotated ellipsoidal bubbles in a liquid cylinder, parallel beam.

The sample (:func:`column_phantom`) is an upright liquid cylinder centred on
the rotation axis, ``radius_fraction`` of the field of view's radius wide
and taller than the detector, filled to a gas fraction of ``gas_fraction``
with polydisperse, randomly rotated ellipsoids: equivalent radii
log-normal about a median chosen so that about ``n_bubbles`` bubbles reach
into the detector's rows, semi-axes ``r exp(g_i)`` with zero-sum
log-normal ``g`` (volume-preserving, axis ratios up to about 1.35), and
uniformly random orientations. Bubbles are disjoint with a film of at least
``gap`` mm (by default 5 % of the median radius): every ellipsoid is tested as its copy scaled by
``1 + gap / (2 a_min)`` (which contains all points within ``gap / 2`` of
it), and the packing is a collective rearrangement of those copies from
uniformly random centres: each overlapping pair (Perram-Wertheim contact
function ``F < 1``) is pushed apart along its centre line by 1.6 times the
distance that would make it touch (``|r| (1 / sqrt(F) - 1)``), shared in inverse
proportion to the volumes, with the centres kept inside the cylinder,
until no pair overlaps. Bubbles cut by the detector's top and bottom rows
follow from the column's height.

The scan (:func:`simulate_column`) is a parallel beam over ``arc`` degrees
with ``k x k`` sub-rays per pixel whose chords through every ellipsoid and
the cylinder are exact (:mod:`bubsub.core.foam.ellipsoids`), and Poisson
noise at ``photons`` counts per flat-field pixel
(:func:`bubsub.core.foam.simulate.add_poisson_noise`). Its ``background`` is
the noise-free projection of the cylinder alone. :func:`write_column`
writes the simulation folder that ``bubsub reconstruct`` and ``bubsub
evaluate`` read (``scan.h5``, ``truth.ply``, ``phantom.json``) plus
``truth.csv`` with each bubble's analytic parameters.

Defaults: 40 projections of 256 x 768 pixels of 12 um over 180 degrees,
liquid 0.1/mm, gas 0, I0 = 1e4; :data:`COLUMN_PRESETS` are the ~150, ~600
and ~2400 bubble columns of the scale benchmark (smaller bubbles for more).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
from scipy.optimize import brentq
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from bubsub.core.foam.checks import count, finite, frozen, nonneg, positive, rng_from_seed
from bubsub.core.foam.ellipsoids import (contact_function, ellipsoid_mesh, ellipsoid_volumes, fraction_below,
                                         project_cylinder, project_ellipsoids, shape_matrices)
from bubsub.core.projection.mesh import equivalent_radius
from bubsub.core.foam.simulate import add_poisson_noise
from bubsub.core.io.atomic import atomic_write_text
from bubsub.core.io.meshio import write_ply
from bubsub.core.io.scanfile import Scan, write_scan
from bubsub.core.io.tables import write_csv
from bubsub.core.projection.geometry import ScanGeometry

__all__ = ["ColumnPhantom", "column_phantom", "expected_visible", "column_geometry", "simulate_column", "write_column", "COLUMN_PRESETS",
           "TRUTH_COLUMN_INFO"]

#: Bubble counts of the scale benchmark's columns (all on the default 256 x 768 detector).
COLUMN_PRESETS = (150, 600, 2400)

_LOG_SPREAD_CLIP = (0.6, 1.6)  # equivalent radii are clipped to this range times the median
_ASPECT_CLIP = 0.15  # largest |log| deviation of a semi-axis from the equivalent radius
_GAP = 0.05  # default film between bubbles, times the median equivalent radius
_OVERPUSH = 1.6  # pairs are pushed this many times the distance that makes them touch (fewest steps measured)


@dataclasses.dataclass(frozen=True, eq=False)
class ColumnPhantom:
    """Ellipsoidal bubbles in an upright liquid cylinder, seen by a parallel-beam detector.

    Attributes
    ----------
    centres : (n, 3) float
        mm; the rotation axis is the z axis, the detector's rows span ``|z| <= fov_half_height``.
    axes : (n, 3) float
        Semi-axes, mm.
    rotations : (n, 3, 3) float
        Columns: the principal directions.
    radius : float
        Liquid cylinder radius, mm.
    z_range : (2,) float
        Liquid cylinder bottom and top, mm (beyond the detector's rows).
    rows, cols : int
        Detector size.
    pixel_size : float
        mm.
    liquid_attenuation, gas_attenuation : float
        1/mm.
    gap : float
        Smallest film between two bubbles and between a bubble and the wall, mm.
    median_radius : float
        Median equivalent radius the sizes were drawn about, mm.
    seed : int
    """

    centres: np.ndarray
    axes: np.ndarray
    rotations: np.ndarray
    radius: float
    z_range: tuple
    rows: int
    cols: int
    pixel_size: float
    liquid_attenuation: float
    gas_attenuation: float
    gap: float
    median_radius: float
    seed: int

    @property
    def contrast(self):
        """Bubble attenuation relative to the liquid, ``gas - liquid`` (1/mm)."""
        return self.gas_attenuation - self.liquid_attenuation

    @property
    def fov_radius(self):
        """Radius of the cylinder every projection sees, mm (half the detector width)."""
        return 0.5 * self.cols * self.pixel_size

    @property
    def fov_half_height(self):
        """Half the detector height, mm."""
        return 0.5 * self.rows * self.pixel_size

    @property
    def shapes(self):
        """(n, 3, 3) shape matrices ``R diag(a^2) R^T``."""
        return shape_matrices(self.axes, self.rotations)

    @property
    def volumes(self):
        """(n,) mm^3."""
        return ellipsoid_volumes(self.axes)

    def fraction_in_fov(self):
        """(n,) exact fraction of each bubble's volume within the detector's rows."""
        h, s = self.fov_half_height, self.shapes
        return fraction_below(self.centres, s, h) - fraction_below(self.centres, s, -h)

    def cut(self):
        """``(top, bottom)``: (n,) bool, the bubbles crossing the top / bottom row's edge."""
        h = self.fov_half_height
        ez = np.sqrt(self.shapes[:, 2, 2])
        z = self.centres[:, 2]
        return (np.abs(z - h) < ez), (np.abs(z + h) < ez)

    @property
    def visible(self):
        """(n,) bool: the bubbles reaching into the detector's rows (the truth of a scan)."""
        return self.fraction_in_fov() > 0

    @property
    def gas_fraction(self):
        """Gas volume over liquid-cylinder volume within the detector's rows."""
        return float((self.volumes * self.fraction_in_fov()).sum() / (np.pi * self.radius**2 * 2 * self.fov_half_height))

    def truth_meshes(self, subdivisions=4):
        """Meshes of the visible bubbles (:func:`ellipsoid_mesh`), in the order of ``np.flatnonzero(visible)``."""
        idx = np.flatnonzero(self.visible)
        if not len(idx):
            return []
        first = ellipsoid_mesh(self.centres[idx[0]], self.axes[idx[0]], self.rotations[idx[0]], self.contrast,
                               subdivisions)
        return [first] + [ellipsoid_mesh(self.centres[b], self.axes[b], self.rotations[b], self.contrast,
                                         subdivisions, template=first) for b in idx[1:]]

    def __repr__(self):
        return (f"ColumnPhantom({len(self.centres)} bubbles, {int(self.visible.sum())} in the detector's rows, "
                f"radius={self.radius:.4g} mm, gas fraction {self.gas_fraction:.3f}, seed={self.seed!r})")


def expected_visible(median, n_target, fov_half, area, gas_fraction, spread):
    """Bubbles expected within the rows for a median radius, minus ``n_target`` (a root finder's function).

    Parameters
    ----------
    median : float
        Median bubble radius, mm (log-normal sizes of ``spread``).
    n_target : float
        Bubbles wanted in view.
    fov_half : float
        Half the height of the rows seen, mm.
    area : float
        Cross-section of the liquid column, mm^2.
    gas_fraction : float
    spread : float
        Standard deviation of the log of the size factor.

    Returns
    -------
    float
    """
    mean_cube = np.exp(4.5 * spread**2)  # E[s^3] of the log-normal size factor
    mean_r = median * np.exp(0.5 * spread**2)
    density = gas_fraction / (4.0 / 3.0 * np.pi * median**3 * mean_cube)
    return density * area * (2.0 * fov_half + 2.0 * mean_r) - n_target


def column_phantom(n_bubbles=600, *, seed=0, rows=256, cols=768, pixel_size=0.012, gas_fraction=0.4,
                   radius_fraction=0.9, polydispersity=0.2, aspect=0.1, gap=None, liquid_attenuation=0.1,
                   gas_attenuation=0.0, max_iterations=20000):
    """A random foam column for a parallel-beam detector of ``rows x cols`` pixels.

    Parameters
    ----------
    n_bubbles : int
        About this many bubbles reach into the detector's rows (sets the median radius).
    seed : int
    rows, cols : int
        Detector size; the field of view is ``cols * pixel_size`` wide and ``rows * pixel_size`` high.
    pixel_size : float
        mm.
    gas_fraction : float
        Target gas volume over liquid-cylinder volume, in (0, 0.55].
    radius_fraction : float
        Liquid cylinder radius over the field of view's radius, in (0, 1].
    polydispersity : float
        Standard deviation of the log of the equivalent radius.
    aspect : float
        Standard deviation of the log of each semi-axis about the equivalent radius.
    gap : float, optional
        Smallest liquid film between bubbles, and between a bubble and the cylinder wall, mm
        (default 5 % of the median equivalent radius: 1.3 pixels for the ~600-bubble column).
    liquid_attenuation, gas_attenuation : float
        1/mm.
    max_iterations : int
        Relaxation steps before giving up.

    Returns
    -------
    ColumnPhantom

    Raises
    ------
    ValueError
        On bad parameters, or when the bubbles cannot be packed without overlap.
    """
    rng = rng_from_seed(seed)
    n_target = count("n_bubbles", n_bubbles)
    rows, cols = count("rows", rows), count("cols", cols)
    px = positive("pixel_size", pixel_size)
    phi = positive("gas_fraction", gas_fraction)
    if phi > 0.55:
        raise ValueError(f"gas_fraction must be at most 0.55 (random packings of these ellipsoids jam above), got {phi}")
    frac = positive("radius_fraction", radius_fraction)
    if frac > 1:
        raise ValueError(f"radius_fraction must be in (0, 1] (a wider sample is laterally truncated), got {frac}")
    spread, aspect = nonneg("polydispersity", polydispersity), nonneg("aspect", aspect)
    mu_l, mu_g = finite("liquid_attenuation", liquid_attenuation), finite("gas_attenuation", gas_attenuation)
    if mu_l == mu_g:
        raise ValueError("liquid_attenuation and gas_attenuation must differ (the bubbles would be invisible)")
    steps = count("max_iterations", max_iterations)
    radius, half = frac * 0.5 * cols * px, 0.5 * rows * px
    try:
        median = brentq(expected_visible, 1e-4 * radius, radius, args=(n_target, half, np.pi * radius**2, phi, spread))
    except ValueError:
        raise ValueError(f"no bubble size gives {n_target} bubbles in the field of view; ask for more") from None
    gap = _GAP * median if gap is None else nonneg("gap", gap)
    lo, hi = _LOG_SPREAD_CLIP
    biggest = hi * median * np.exp(_ASPECT_CLIP)
    if biggest + gap > 0.5 * radius:
        raise ValueError(f"{n_target} bubbles are too few: their largest ({biggest:.3g} mm) would not fit the "
                         f"{radius:.3g} mm column; ask for more bubbles")
    z_half = half + 3.0 * biggest  # bubble centres lie within |z| <= z_half
    target_volume = phi * np.pi * radius**2 * 2.0 * z_half
    expect = int(target_volume / (4.0 / 3.0 * np.pi * median**3 * np.exp(4.5 * spread**2))) + 1
    r_eq = median * np.clip(np.exp(spread * rng.normal(size=2 * expect + 16)), lo, hi)
    filled = np.cumsum(4.0 / 3.0 * np.pi * r_eq**3)
    if filled[-1] < target_volume:  # pragma: no cover - twice the expected count always fills the column
        raise ValueError("the drawn bubble sizes do not fill the column")
    r_eq = r_eq[: int(np.searchsorted(filled, target_volume)) + 1]
    n = len(r_eq)
    g = aspect * rng.normal(size=(n, 3))
    g = np.clip(g - g.mean(axis=1, keepdims=True), -_ASPECT_CLIP, _ASPECT_CLIP)
    g -= g.mean(axis=1, keepdims=True)
    axes = r_eq[:, None] * np.exp(g)

    rotations = Rotation.random(n, random_state=rng).as_matrix()
    centres = _pack(rng, axes, rotations, radius, z_half, gap, steps)
    return ColumnPhantom(
        centres=frozen(centres), axes=frozen(axes), rotations=frozen(rotations), radius=float(radius),
        z_range=(-z_half - biggest - gap, z_half + biggest + gap), rows=rows, cols=cols, pixel_size=px,
        liquid_attenuation=mu_l, gas_attenuation=mu_g, gap=gap, median_radius=float(median), seed=int(seed))


def _pack(rng, axes, rotations, radius, z_half, gap, steps):
    """Centres of disjoint ellipsoids (with ``gap``) inside the cylinder: collective rearrangement."""
    grown = axes * (1.0 + gap / (2.0 * axes.min(axis=1)))[:, None]
    s = shape_matrices(grown, rotations)
    bound = grown.max(axis=1)
    a, b, d = s[:, 0, 0], s[:, 0, 1], s[:, 1, 1]
    shadow = np.sqrt(0.5 * (a + d) + np.sqrt(0.25 * (a - d) ** 2 + b * b))  # largest half-width seen from above
    rho_max = radius - 0.5 * gap - shadow
    if np.any(rho_max <= 0):
        raise ValueError("a bubble is wider than the liquid column; ask for more (smaller) bubbles")
    n = len(axes)
    rho = rho_max * np.sqrt(rng.uniform(size=n))
    theta = rng.uniform(0.0, 2.0 * np.pi, n)
    x = np.stack([rho * np.cos(theta), rho * np.sin(theta), rng.uniform(-z_half, z_half, n)], axis=1)
    weight = ellipsoid_volumes(grown)
    for _ in range(steps):
        i, j = cKDTree(x).query_pairs(2.0 * bound.max(), output_type="ndarray").T
        r = x[j] - x[i]
        dist = np.linalg.norm(r, axis=1)
        near = dist < bound[i] + bound[j]
        i, j, r, dist = i[near], j[near], r[near], dist[near]
        f = contact_function(s[i], s[j], r, iterations=24)
        hit = f < 1.0
        if not hit.any():
            return x
        i, j, r, dist, f = i[hit], j[hit], r[hit], dist[hit], f[hit]
        safe = np.maximum(dist, 1e-12)
        push = (safe * (1.0 / np.sqrt(np.maximum(f, 1e-12)) - 1.0) * _OVERPUSH + 1e-6)[:, None] * (r / safe[:, None])
        share = (weight[j] / (weight[i] + weight[j]))[:, None]
        move = np.zeros_like(x)
        np.add.at(move, i, -share * push)
        np.add.at(move, j, (1.0 - share) * push)
        x += move
        rho = np.hypot(x[:, 0], x[:, 1])
        x[:, :2] *= np.minimum(1.0, rho_max / np.maximum(rho, 1e-12))[:, None]
        np.clip(x[:, 2], -z_half, z_half, out=x[:, 2])
    raise ValueError(f"could not pack {n} bubbles without overlap in {steps} relaxation steps; lower gas_fraction "
                     f"or gap, or raise max_iterations")


def column_geometry(phantom, n_angles=40, arc=180.0):
    """The parallel-beam scan of a column: ``n_angles`` equiangular views over ``arc`` degrees."""
    n = count("n_angles", n_angles)
    arc = positive("arc", arc)
    angles = np.linspace(0.0, np.radians(arc), n, endpoint=False)
    return ScanGeometry.parallel(angles, pixel_size=phantom.pixel_size, cols=phantom.cols, rows=phantom.rows)


def simulate_column(phantom, *, n_angles=40, arc=180.0, photons=1e4, supersampling=2, noise_seed=None):
    """The scan of a column: exact sub-ray chords, Poisson noise, the cylinder's projection as background.

    Parameters
    ----------
    phantom : ColumnPhantom
    n_angles : int
    arc : float
        Degrees.
    photons : float or None
        Flat-field counts per pixel (I0); None gives noise-free data.
    supersampling : int
        Sub-rays per pixel and axis.
    noise_seed : int, optional
        Defaults to the phantom's seed.

    Returns
    -------
    Scan
        ``data`` (line integrals), ``background`` (noise-free cylinder),
        ``bubble_contrast``, simulation settings in ``attrs``.
    """
    if not isinstance(phantom, ColumnPhantom):
        raise ValueError(f"phantom must be a ColumnPhantom, got {type(phantom).__name__}")
    geometry = column_geometry(phantom, n_angles, arc)
    k = count("supersampling", supersampling)
    background = project_cylinder(geometry, phantom.radius, phantom.z_range, phantom.liquid_attenuation, k)
    clean = project_ellipsoids(geometry, phantom.centres, phantom.axes, phantom.rotations, phantom.contrast, k,
                               out=background.copy())
    seed = phantom.seed if noise_seed is None else noise_seed
    data = clean if photons is None else add_poisson_noise(clean, photons, seed)
    attrs = {"simulated": 1, "method": "analytic", "phantom": "column", "photons": 0.0 if photons is None else
             float(photons), "phantom_seed": phantom.seed, "n_bubbles": int(phantom.visible.sum()),
             "supersampling": k}
    if photons is not None:
        attrs["noise_seed"] = int(seed)
    return Scan(data=np.asarray(data, dtype=np.float32), geometry=geometry,
                background=background.astype(np.float32), bubble_contrast=phantom.contrast, attrs=attrs)


#: ``column: (unit, meaning)`` of ``truth.csv``.
TRUTH_COLUMN_INFO = {
    "id": ("", "bubble id: its bubble_id in truth.ply"),
    **{f"centre_{a}_mm": ("mm", f"{a} coordinate of the ellipsoid's centre") for a in "xyz"},
    **{f"semi_axis_{k}_mm": ("mm", f"semi-axis {k} (along column {k} of the rotation)") for k in (1, 2, 3)},
    **{f"rotation_{i}{j}": ("1", f"rotation matrix entry ({i}, {j}); its columns are the principal directions")
       for i in (1, 2, 3) for j in (1, 2, 3)},
    "volume_mm3": ("mm^3", "ellipsoid volume 4/3 pi a1 a2 a3"),
    "volume_in_fov_mm3": ("mm^3", "volume within the detector's rows (exact)"),
    "equivalent_diameter_mm": ("mm", "diameter of the ball of the same volume"),
    "cut_top": ("1", "1 if the bubble crosses the top edge of the field of view"),
    "cut_bottom": ("1", "1 if the bubble crosses the bottom edge of the field of view"),
}


def truth_grid(phantom, voxel=None):
    """The evaluation grid: the liquid cylinder's square times the detector's rows, ``voxel`` mm (2 pixels)."""
    voxel = 2.0 * phantom.pixel_size if voxel is None else positive("grid voxel", voxel)
    n_xy = int(np.ceil(2.0 * phantom.radius / voxel))
    n_z = max(1, int(round(2.0 * phantom.fov_half_height / voxel)))
    half_xy, h = 0.5 * n_xy * voxel, phantom.fov_half_height
    return (n_z, n_xy, n_xy), (-half_xy, half_xy, -half_xy, half_xy, -h, h)


def write_column(out, phantom, scan, *, truth_subdivisions=4, grid_voxel=None):
    """Write a column's simulation folder: ``scan.h5``, ``truth.ply``, ``truth.csv`` (+ sidecar), ``phantom.json``.

    Parameters
    ----------
    out : str or Path
        Folder (created).
    phantom : ColumnPhantom
    scan : Scan
        :func:`simulate_column` of the phantom.
    truth_subdivisions : int
        Icosphere subdivisions of the truth meshes (4: 5120 triangles each).
    grid_voxel : float, optional
        Evaluation grid voxel, mm (default two detector pixels).

    Returns
    -------
    files : list of Path
        Everything written (for the output folder's manifest).
    meta : dict
        The contents of ``phantom.json``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    idx = np.flatnonzero(phantom.visible)
    in_fov = phantom.fraction_in_fov()
    top, bottom = phantom.cut()
    vol = phantom.volumes
    rows = []
    for n, b in enumerate(idx):
        row = {"id": n, **{f"centre_{a}_mm": float(phantom.centres[b, i]) for i, a in enumerate("xyz")},
               **{f"semi_axis_{k + 1}_mm": float(phantom.axes[b, k]) for k in range(3)},
               **{f"rotation_{i + 1}{j + 1}": float(phantom.rotations[b, i, j]) for i in range(3) for j in range(3)},
               "volume_mm3": float(vol[b]), "volume_in_fov_mm3": float(vol[b] * in_fov[b]),
               "equivalent_diameter_mm": 2.0 * equivalent_radius(vol[b], 3),
               "cut_top": int(top[b]), "cut_bottom": int(bottom[b])}
        rows.append(row)
    files = [write_scan(out / "scan.h5", scan)]
    files.append(write_ply(out / "truth.ply", phantom.truth_meshes(truth_subdivisions)))
    files.append(write_csv(out / "truth.csv", rows, list(TRUTH_COLUMN_INFO), describe=TRUTH_COLUMN_INFO,
                           title="column truth: one analytic ellipsoid per bubble in the field of view"))
    files.append(out / "truth.csv-metadata.json")
    shape, extent = truth_grid(phantom, grid_voxel)
    g = scan.geometry
    meta = {"phantom": "column", "ndim": 3, "seed": phantom.seed, "size": [2 * phantom.radius, 2 * phantom.radius,
            phantom.z_range[1] - phantom.z_range[0]], "liquid_attenuation": phantom.liquid_attenuation,
            "bubble_contrast": phantom.contrast, "bubbles": len(idx), "grid_shape": list(shape),
            "grid_extent": list(extent), "angles": g.n_angles, "photons": scan.attrs.get("photons"),
            "beam": "parallel", "truth": "truth.ply", "truth_table": "truth.csv",
            "column": {"radius_mm": phantom.radius, "z_range_mm": list(phantom.z_range),
                       "fov_radius_mm": phantom.fov_radius, "fov_half_height_mm": phantom.fov_half_height,
                       "rows": phantom.rows, "cols": phantom.cols, "pixel_size_mm": phantom.pixel_size,
                       "gas_fraction_in_fov": phantom.gas_fraction, "median_radius_mm": phantom.median_radius,
                       "gap_mm": phantom.gap, "bubbles_cut_top": int((top & phantom.visible).sum()),
                       "bubbles_cut_bottom": int((bottom & phantom.visible).sum()),
                       "bubbles_generated": len(phantom.centres), "supersampling": scan.attrs.get("supersampling"),
                       "truth_subdivisions": truth_subdivisions}}
    files.append(out / "phantom.json")
    atomic_write_text(out / "phantom.json", json.dumps(meta, indent=2))
    return files, meta
