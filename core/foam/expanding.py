"""Expanding wet foam for dynamic (4D) scans, in the spirit of Pelt's ExpandingFoamPhantom.

The foam at the end of the scan (``t = 1``) is a random static foam
(:func:`bubsub.core.foam.phantoms.foam2d` / ``foam3d``). Earlier, every bubble
is smaller: its radius follows its own random growth curve

    r_b(t) = R_b (f_b + (1 - f_b) t^p_b),   f_b ~ U(start_range),  p_b ~ U(0.5, 2)

(``R_b`` its final radius; shapes are kept, scaled about the centre). The
liquid volume is kept: the container's side scales by ``s(t)`` with
``(s L)^d - gas(t) = L^d - gas(1)``, so the sample expands as the gas grows,
and bubble centres move with it (``c_b(t) = s(t) c_b``). Radii are capped at
``s(t) R_b``, which keeps every pair of bubbles disjoint at all times
(centre distances scale by ``s``, radii by at most ``s``).

``at(t)`` gives the foam at any time as a static :class:`FoamPhantom`;
a dynamic simulation calls it for every projection, so the foam moves during
each subscan.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from bubsub.core.foam.phantoms import FoamPhantom, foam2d, foam3d, liquid_box, liquid_square
from bubsub.core.projection.mesh import Mesh, Polygon
from bubsub.core.foam.simulate import simulated_scan
from bubsub.core.projection.projector import MeshProjector

__all__ = ["ExpandingFoam", "expanding2d", "expanding3d"]


@dataclasses.dataclass(frozen=True, eq=False)
class ExpandingFoam:
    """A foam that grows from ``t = 0`` to ``t = 1`` (see the module docstring).

    Attributes
    ----------
    final : FoamPhantom
        The foam at ``t = 1``.
    start_fraction : (n_bubbles,) float
        ``f_b``: radius at ``t = 0`` over the final radius.
    exponent : (n_bubbles,) float
        ``p_b`` of the growth curve.
    seed : int
    """

    final: FoamPhantom
    start_fraction: np.ndarray
    exponent: np.ndarray
    seed: int

    @property
    def ndim(self):
        return self.final.ndim

    @property
    def n_bubbles(self):
        return len(self.final.bubbles)

    def __repr__(self):
        name = "expanding2d" if self.ndim == 2 else "expanding3d"
        return f"{name}(seed={self.seed!r}, n_bubbles={self.n_bubbles})"

    def _gas(self, rel):
        base = np.array([b.area if self.ndim == 2 else b.volume for b in self.final.bubbles])
        return float(np.sum(base * rel ** self.ndim))

    def state(self, t):
        """``(relative radii (n_bubbles,), container scale s)`` at time ``t`` in [0, 1]."""
        t = float(t)
        if not 0.0 <= t <= 1.0:
            raise ValueError(f"time must be in [0, 1], got {t}")
        rel = self.start_fraction + (1.0 - self.start_fraction) * t ** self.exponent
        d = self.ndim
        full = float(np.prod(self.final.size))
        liquid = full - self._gas(np.ones(self.n_bubbles))
        s = 1.0
        for _ in range(4):  # the cap lowers the gas, which lowers s: a few rounds settle it
            s = ((liquid + self._gas(rel)) / full) ** (1.0 / d)
            rel = np.minimum(rel, s)
        return rel, s

    def at(self, t):
        """The foam at time ``t`` in [0, 1] as a static :class:`FoamPhantom` (same bubble order = ids)."""
        rel, s = self.state(t)
        f = self.final
        bubbles = []
        for b, (mesh, c) in enumerate(zip(f.bubbles, f.centres)):
            v = s * c + rel[b] * (mesh.vertices - c)
            bubbles.append(Polygon(v, mesh.attenuation) if self.ndim == 2 else Mesh(v, mesh.faces, mesh.attenuation))
        size = tuple(s * x for x in f.size)
        liquid = liquid_square(size[0], f.liquid_attenuation) if self.ndim == 2 else liquid_box(size, f.liquid_attenuation)
        return FoamPhantom(liquid=liquid, bubbles=tuple(bubbles), size=size,
                           liquid_attenuation=f.liquid_attenuation, gas_attenuation=f.gas_attenuation,
                           centres=s * np.asarray(f.centres), radii=rel * np.asarray(f.radii), seed=f.seed)


def _growth(rng, n, start_range):
    lo, hi = (float(x) for x in start_range)
    if not 0 < lo <= hi <= 1:
        raise ValueError(f"start_range must satisfy 0 < lo <= hi <= 1, got {start_range!r}")
    return rng.uniform(lo, hi, n), rng.uniform(0.5, 2.0, n)


def expanding2d(seed, n_bubbles=30, start_range=(0.45, 0.75), **foam):
    """Expanding 2D foam: :func:`foam2d` (``n_bubbles``, ``**foam``) is the final state.

    The outlines have 128 vertices (the fitted model has 9 control points).
    """
    final = foam2d(seed, n_bubbles=n_bubbles, **foam)
    rng = np.random.default_rng([int(seed), 4])
    f, p = _growth(rng, n_bubbles, start_range)
    return ExpandingFoam(final, f, p, int(seed))


def expanding3d(seed, n_bubbles=20, start_range=(0.45, 0.75), subdivisions=3, **foam):
    """Expanding 3D foam: :func:`foam3d` is the final state, icospheres of ``subdivisions``
    (3: 642 vertices, finer than the fitted 42-point control mesh) smoothly deformed."""
    final = foam3d(seed, n_bubbles=n_bubbles, subdivisions=subdivisions, **foam)
    rng = np.random.default_rng([int(seed), 4])
    f, p = _growth(rng, n_bubbles, start_range)
    return ExpandingFoam(final, f, p, int(seed))


def simulate_expanding(foam, geometry, *, projections_per_subscan, photons=None, seed=0,
                       seconds_per_projection=0.01, supersampling=1):
    """Simulated dynamic scan of an expanding foam, the foam updated between every projection.

    Projection ``i`` of ``n`` sees the foam at ``t_i = (i + 0.5) / n``. Truth
    projections come from the phantom's fine outlines / meshes (128-vertex
    polygons, 642-vertex meshes) through the exact mesh projector, not from
    the fitted subdivision model.

    Parameters
    ----------
    foam : ExpandingFoam
    geometry : ScanGeometry
        All projections in acquisition order, one row each.
    projections_per_subscan : int
        Must divide ``geometry.n_angles``.
    photons : float, optional
        Flat-field photon count (Poisson noise); None: noise-free.
    seed : int
        Seed of the noise.
    seconds_per_projection : float
        ``/exchange/time`` step, s.

    Returns
    -------
    scan : Scan
        With ``time``, ``projections_per_subscan`` and a per-projection
        ``background`` (the liquid alone, which expands too).
    mid_times : (n_subscans,) float
        Each subscan's mid-time in [0, 1] (where its truth is taken).
    """
    n = geometry.n_angles
    k = int(projections_per_subscan)
    if k < 1 or n % k:
        raise ValueError(f"projections_per_subscan = {k} must divide the {n} projections")
    if geometry.ndim != foam.ndim:
        raise ValueError(f"a {foam.ndim}D foam needs a {foam.ndim}D geometry, got {geometry.ndim}D")
    t = (np.arange(n) + 0.5) / n
    clean = np.empty(geometry.shape, np.float32)
    background = np.empty(geometry.shape, np.float32)
    for i in range(n):
        phantom = foam.at(t[i])
        proj = MeshProjector(geometry[i:i + 1], supersampling=supersampling)
        clean[i] = proj.forward(phantom.items)[0]
        background[i] = proj.forward([phantom.liquid])[0]
    scan = simulated_scan(foam.final, geometry, clean, background, photons, seed, "mesh",
                   {"dynamic": 1, "supersampling": supersampling})
    scan.time = np.arange(n) * float(seconds_per_projection)
    scan.projections_per_subscan = k
    return scan, t.reshape(-1, k).mean(axis=1)
