"""Wet-foam phantoms: gas bubbles in a liquid container, in 2D and 3D.

A phantom is a liquid container (a square polygon in 2D, a box mesh in 3D)
with attenuation ``liquid_attenuation`` plus disjoint bubbles whose
attenuation is the *contrast* ``gas_attenuation - liquid_attenuation``
(-0.1/mm by default). Projections add up, so the full scene is
``[phantom.liquid] + phantom.bubbles`` (:attr:`FoamPhantom.items`), and
``projection(scene) - projection(liquid)`` is the projection of the bubbles
alone, which is what BubSub fits.

Defaults follow the paper (Renders et al., BubSub): 2D a 10 mm square of
liquid at 0.1/mm (water at 16 keV, 1/cm) with polydisperse, slightly
non-circular bubbles of radius 0.3-0.8 mm, rasterised on up to 2000 x 2000
pixels; 3D a 20 x 20 x 10 mm box with sparse spherical bubbles.

Every generator takes a ``seed`` and uses its own
:class:`numpy.random.Generator`, so a phantom is reproducible from its
arguments.
"""

from __future__ import annotations

import dataclasses
import numbers

import numpy as np

from bubsub.core.foam.checks import (unit_icosphere, rng_from_seed, count, finite, positive, nonneg, fraction,
                                     value_range, size_vector, frozen)
from bubsub.core.foam.containers import liquid_box, liquid_square
from bubsub.core.foam.packing import fourier_perturbation, smooth_sphere_perturbation, place
from bubsub.core.projection.mesh import Mesh, Polygon
from bubsub.core.projection.masks import bubble_mask, label_image, rasterize

__all__ = [
    "FoamPhantom",
    "foam2d",
    "foam3d",
    "foam3d_benchmark",
    "BENCHMARK_SEED",
]

#: Seed of the fixed 3D benchmark scene (:func:`foam3d_benchmark`).
BENCHMARK_SEED = 20240611


@dataclasses.dataclass(frozen=True, eq=False)
class FoamPhantom:
    """Liquid container with gas bubbles (2D polygons or 3D meshes).

    Attributes
    ----------
    liquid : Polygon or Mesh
        The container, attenuation ``liquid_attenuation``.
    bubbles : tuple of Polygon or tuple of Mesh
        Disjoint bubbles inside the container, attenuation ``contrast``.
    size : (2,) or (3,) tuple of float
        Container side lengths (x, y[, z]), mm; the container is centred at
        the origin.
    liquid_attenuation, gas_attenuation : float
        1/mm.
    centres : (n_bubbles, ndim) float
        Nominal bubble centres, mm.
    radii : (n_bubbles,) float
        Nominal (mean) bubble radii, mm.
    seed : int or None
        Seed the phantom was generated from.
    """

    liquid: object
    bubbles: tuple
    size: tuple
    liquid_attenuation: float
    gas_attenuation: float
    centres: np.ndarray
    radii: np.ndarray
    seed: int | None = None

    @property
    def ndim(self):
        """2 or 3."""
        return len(self.size)

    def __repr__(self):
        return (
            f"FoamPhantom({self.ndim}D, {len(self.bubbles)} bubbles, size={self.size}, "
            f"liquid={self.liquid_attenuation!r}, gas={self.gas_attenuation!r}, seed={self.seed!r})"
        )

    @property
    def contrast(self):
        """Bubble attenuation relative to the liquid, ``gas - liquid`` (1/mm)."""
        return self.gas_attenuation - self.liquid_attenuation

    @property
    def items(self):
        """The full scene for a projector: ``[liquid] + bubbles``."""
        return [self.liquid, *self.bubbles]

    @property
    def extent(self):
        """The container's extent ``(xmin, xmax, ymin, ymax[, zmin, zmax])``, mm."""
        out = []
        for s in self.size:
            out += [-s / 2.0, s / 2.0]
        return tuple(out)

    @property
    def gas_fraction(self):
        """Fraction of the container's area (volume) taken by bubbles."""
        if self.ndim == 2:
            total = sum(b.area for b in self.bubbles)
            return total / self.liquid.area
        return sum(b.volume for b in self.bubbles) / self.liquid.volume

    def grid(self, shape, extent=None):
        """Normalise a grid request: an int ``n`` means ``n`` pixels along x.

        Parameters
        ----------
        shape : int or tuple of int
            ``n`` gives square pixels of side ``size[0] / n`` covering the
            container (2D: ``(n, n)`` for a square; 3D: ``(nz, ny, n)``).
        extent : tuple, optional
            Defaults to :attr:`extent`.

        Returns
        -------
        shape : tuple of int
        extent : tuple of float
        """
        ext = self.extent if extent is None else tuple(extent)
        if isinstance(shape, numbers.Integral) and not isinstance(shape, bool):
            if shape < 1:
                raise ValueError(f"grid size must be a positive integer, got {shape!r}")
            px = (ext[1] - ext[0]) / shape
            sizes = [ext[2 * i + 1] - ext[2 * i] for i in range(len(ext) // 2)]
            counts = [max(1, int(round(s / px))) for s in sizes]
            shape = tuple(reversed(counts))  # (ny, nx) or (nz, ny, nx)
        return tuple(shape), ext

    def attenuation_image(self, shape=2000, extent=None, supersample=1, dtype=np.float64):
        """Rasterised attenuation of the full scene (liquid + bubbles).

        Parameters
        ----------
        shape : int or tuple of int
            See :meth:`grid`; 2D ``(rows, cols)``, 3D ``(slices, rows, cols)``.
        extent : tuple, optional
            Grid extent, mm; defaults to the container.
        supersample : int
            Sub-samples per pixel and axis (partial volumes at the edges).
        dtype : numpy dtype

        Returns
        -------
        ndarray, shape ``shape``
            1/mm; row 0 at y max (see :mod:`bubsub.core.projection.masks`).
        """
        shp, ext = self.grid(shape, extent)
        return rasterize(self.items, shp, ext, supersample=supersample, dtype=dtype)

    def liquid_image(self, shape=2000, extent=None, supersample=1, dtype=np.float64):
        """Rasterised attenuation of the liquid container alone (the background)."""
        shp, ext = self.grid(shape, extent)
        return rasterize([self.liquid], shp, ext, supersample=supersample, dtype=dtype)

    def labels(self, shape=2000, extent=None):
        """Label image: 0 outside bubbles, ``i + 1`` inside ``bubbles[i]`` (int32, shape ``shape``)."""
        shp, ext = self.grid(shape, extent)
        return label_image(self.bubbles, shp, ext)

    def mask(self, shape=2000, extent=None):
        """Bubble mask (bool, shape ``shape``): pixel centres inside any bubble."""
        shp, ext = self.grid(shape, extent)
        return bubble_mask(self.bubbles, shp, ext)


# -- 2D foam ----------------------------------------------------------------------
def foam2d(
    seed,
    n_bubbles=40,
    size=10.0,
    liquid_attenuation=0.1,
    gas_attenuation=0.0,
    radius_range=(0.3, 0.8),
    n_vertices=128,
    perturbation=0.03,
    max_mode=5,
    gap=0.05,
    margin=0.25,
    max_attempts=2000,
    packing="random",
):
    """Random 2D wet foam: polydisperse, slightly non-circular bubbles in a liquid square.

    Radii are drawn uniformly from ``radius_range`` and placed largest
    first at uniformly random positions (random sequential addition),
    rejecting positions closer than ``gap`` to an earlier bubble or than
    ``margin`` to the square's border. With ``packing="dense"`` all bubbles
    start at random positions and overlapping ones are pushed apart until
    none overlaps, which packs a denser foam (``n_bubbles=50`` gives a gas
    fraction of about 0.52; about 60 bubbles is the practical limit).

    Each bubble outline is ``r(t) = r0 (1 + sum_k a_k cos(k t + phi_k))`` for ``k = 2..max_mode``
    with random phases and amplitudes, scaled so that the largest relative
    deviation is between ``perturbation / 2`` and ``perturbation``.

    Parameters
    ----------
    seed : int
        Seed of the random generator.
    n_bubbles : int
        Number of bubbles. The default fills roughly 40 % of a 10 mm square
        (random packing jams at about 45 %; use ``packing="dense"`` for more).
    size : float
        Side of the liquid square, mm (centred at the origin).
    liquid_attenuation, gas_attenuation : float
        1/mm. Bubbles get ``gas - liquid`` (-0.1 by default).
    radius_range : (2,) float
        Smallest and largest mean radius, mm.
    n_vertices : int
        Vertices per bubble outline (counter-clockwise).
    perturbation : float
        Largest relative deviation from a circle, in [0, 0.5).
    max_mode : int
        Highest Fourier mode of the outline (>= 2).
    gap : float
        Smallest distance between two bubbles' bounding circles, mm.
    margin : float
        Smallest distance between a bubble's bounding circle and the border, mm.
    max_attempts : int
        Random positions tried per bubble (then a fine lattice is searched),
        or relaxation steps with ``packing="dense"``.
    packing : {"random", "dense"}
        Random sequential addition, or random start plus relaxation.

    Returns
    -------
    FoamPhantom
        2D phantom; ``bubbles`` are :class:`Polygon` with ``n_vertices``
        vertices.

    Raises
    ------
    ValueError
        On bad parameters, or when the bubbles do not fit.
    """
    rng = rng_from_seed(seed)
    n = count("n_bubbles", n_bubbles)
    side = positive("size", size)
    r_lo, r_hi = value_range("radius_range", radius_range)
    nv = count("n_vertices", n_vertices, minimum=8)
    amp = fraction("perturbation", perturbation)
    kmax = count("max_mode", max_mode, minimum=2)
    gap, margin = nonneg("gap", gap), nonneg("margin", margin)
    liquid_attenuation = finite("liquid_attenuation", liquid_attenuation)
    gas_attenuation = finite("gas_attenuation", gas_attenuation)
    contrast = gas_attenuation - liquid_attenuation

    radii = np.sort(rng.uniform(r_lo, r_hi, n))[::-1]
    # outline shapes first: the bounding radius decides the placement
    t = 2.0 * np.pi * np.arange(nv) / nv
    shapes = np.empty((n, nv))
    for b in range(n):
        shapes[b] = 1.0 + fourier_perturbation(rng, t, kmax, amp)
    bound = radii * shapes.max(axis=1)
    half = side / 2.0 - margin
    centres = place(rng, bound, np.array([half, half]), gap, max_attempts, "square", side, packing)

    bubbles = []
    for b in range(n):
        r = radii[b] * shapes[b]
        v = centres[b] + np.stack([r * np.cos(t), r * np.sin(t)], axis=1)
        bubbles.append(Polygon(v, contrast))
    return FoamPhantom(
        liquid=liquid_square(side, liquid_attenuation),
        bubbles=tuple(bubbles),
        size=(side, side),
        liquid_attenuation=liquid_attenuation,
        gas_attenuation=gas_attenuation,
        centres=frozen(centres),
        radii=frozen(radii),
        seed=seed,
    )


# -- 3D foam ----------------------------------------------------------------------
def foam3d_benchmark():
    """The fixed 3D benchmark scene: 100 spherical bubbles in a 20 x 20 x 10 mm box.

    Bubbles have radii uniform in [0.6, 1.2] mm, are icospheres with 320
    triangles (162 vertices), disjoint with a 0.1 mm gap and at least 0.2 mm
    from the box walls; seed :data:`BENCHMARK_SEED`. Liquid 0.1/mm, gas 0.

    Returns
    -------
    FoamPhantom
        3D phantom (``bubbles`` are 100 :class:`Mesh`, ``liquid`` a 12-triangle box).
    """
    return foam3d(
        BENCHMARK_SEED,
        n_bubbles=100,
        size=(20.0, 20.0, 10.0),
        radius_range=(0.6, 1.2),
        subdivisions=2,
        perturbation=0.0,
        gap=0.1,
        margin=0.2,
    )


def foam3d(
    seed,
    n_bubbles=60,
    size=(20.0, 20.0, 10.0),
    liquid_attenuation=0.1,
    gas_attenuation=0.0,
    radius_range=(0.6, 1.2),
    subdivisions=2,
    perturbation=0.05,
    smoothness=2.0,
    gap=0.1,
    margin=0.2,
    max_attempts=2000,
    packing="random",
):
    """Random 3D wet foam: smoothly deformed, disjoint bubbles in a liquid box.

    Each bubble is an icosphere whose radius varies smoothly over the unit
    sphere: ``r(u) = r0 (1 + f(u))`` with ``f`` a sum of a few random plane
    waves ``cos(k_i . u + phi_i)``, ``|k_i| = smoothness`` (so only low
    spherical-harmonic orders appear), scaled so that the largest relative
    deviation is between ``perturbation / 2`` and ``perturbation``
    (``perturbation=0`` gives spheres). Placement as in :func:`foam2d`.

    Parameters
    ----------
    seed : int
    n_bubbles : int
    size : (3,) float
        Box side lengths (x, y, z), mm; the box is centred at the origin.
    liquid_attenuation, gas_attenuation : float
        1/mm; bubbles get ``gas - liquid``.
    radius_range : (2,) float
        Smallest and largest mean radius, mm.
    subdivisions : int
        Icosphere subdivisions (2: 320 triangles per bubble).
    perturbation : float
        Largest relative radial deviation, in [0, 0.5).
    smoothness : float
        Wave number of the deformation on the unit sphere (larger: bumpier).
    gap, margin : float
        Smallest bubble-bubble and bubble-wall distances, mm.
    max_attempts : int
    packing : {"random", "dense"}
        See :func:`foam2d`.

    Returns
    -------
    FoamPhantom
        3D phantom; ``bubbles`` are :class:`Mesh`.

    Raises
    ------
    ValueError
        On bad parameters, or when the bubbles do not fit.
    """
    rng = rng_from_seed(seed)
    n = count("n_bubbles", n_bubbles)
    box = size_vector(size, 3)
    r_lo, r_hi = value_range("radius_range", radius_range)
    amp = fraction("perturbation", perturbation)
    smooth = positive("smoothness", smoothness)
    gap, margin = nonneg("gap", gap), nonneg("margin", margin)
    liquid_attenuation = finite("liquid_attenuation", liquid_attenuation)
    gas_attenuation = finite("gas_attenuation", gas_attenuation)
    contrast = gas_attenuation - liquid_attenuation
    unit_v, faces = unit_icosphere(subdivisions)

    radii = np.sort(rng.uniform(r_lo, r_hi, n))[::-1]
    shapes = np.ones((n, len(unit_v)))
    if amp > 0:
        for b in range(n):
            shapes[b] = 1.0 + smooth_sphere_perturbation(rng, unit_v, smooth, amp)
    bound = radii * shapes.max(axis=1)
    half = np.array(box) / 2.0 - margin
    centres = place(rng, bound, half, gap, max_attempts, "box", box, packing)

    bubbles = tuple(
        Mesh(centres[b] + (radii[b] * shapes[b])[:, None] * unit_v, faces, contrast) for b in range(n)
    )
    return FoamPhantom(
        liquid=liquid_box(box, liquid_attenuation),
        bubbles=bubbles,
        size=tuple(box),
        liquid_attenuation=liquid_attenuation,
        gas_attenuation=gas_attenuation,
        centres=frozen(centres),
        radii=frozen(radii),
        seed=seed,
    )
