"""A flowing, coarsening foam column for dynamic (4D) parallel-beam scans.

The foam is a :func:`~bubsub.core.foam.column.column_phantom` (polydisperse,
randomly rotated ellipsoids packed with a thin liquid film in an upright
liquid cylinder), packed tall enough that the bubbles flowing through the
detector's rows during the whole scan are there from the start. Time ``t`` is
counted in subscans (projection ``j`` of ``P`` per subscan is at
``t_j = (j + 0.5) / P``, subscan ``k``'s mid-time is ``k + 0.5``); over it:

* **Plug flow.** Every centre moves up by ``flow`` pixels per subscan
  (``z_b(t) = z_b(0) + v t``): bubbles enter the field of view through the
  bottom row and leave through the top one. Relative positions are fixed,
  so the flow alone never makes two bubbles overlap.
* **Coarsening.** The smallest ``vanishing`` fraction of the bubbles (by
  volume) shrink to nothing, each at its own random time ``t_v`` in the
  scan's middle 80 %, with ``r^2`` falling linearly
  (``r_b(t) = r_b(0) sqrt(1 - t / t_v)``, the diffusive coarsening law of a
  small bubble). Their gas goes to the bubbles larger than the median, in
  proportion to how much each can grow before touching a neighbour (the
  largest factor ``s_b`` with ``F_bj / s_b^2 >= 1`` for every neighbour's
  Perram-Wertheim contact function ``F_bj``): the growers fill their films
  and come into contact. Gas is conserved exactly unless the growers cannot
  take it all (``gas_kept`` says how much is).
* **Coalescence.** ``coalescences`` pairs of nearly touching neighbours
  (smallest contact function, neither a vanishing bubble) merge at random
  times in the scan's middle 60 %, while both are near the middle of the
  rows: from then on they are one ellipsoid with the pair's summed volume
  and the union's second moments (its centre the volume-weighted centroid,
  its principal axes those of the union's inertia), under a new id. A pair
  is taken only if that ellipsoid stays clear of every neighbour grown to
  its largest size.

Every bubble keeps its shape (semi-axes scale together) and orientation.
:meth:`FlowingFoam.at` gives the foam at any time; its scan, events and
simulation folder are :mod:`bubsub.core.foam.flowing_scan`.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.optimize import brentq
from scipy.spatial import cKDTree

from bubsub.core.foam.checks import count, fraction, nonneg, positive, rng_from_seed
from bubsub.core.foam.column import ColumnPhantom, column_phantom, expected_visible
from bubsub.core.foam.ellipsoids import contact_function, ellipsoid_volumes, fraction_below, shape_matrices

__all__ = ["FlowingFoam", "FoamState", "flowing_foam", "FLOWING_DEFAULTS"]

#: The defaults of :func:`flowing_foam` and :func:`~bubsub.core.foam.flowing_scan.simulate_flowing`: a ~150-bubble column on 128 x 384 pixels.
FLOWING_DEFAULTS = {"n_bubbles": 150, "rows": 128, "cols": 384, "pixel_size": 0.012, "subscans": 12,
                    "projections_per_subscan": 40, "flow": 4.0, "vanishing": 0.12, "coalescences": 4,
                    "photons": 1e4}

_GAP = 0.06  # packing film, times the median equivalent radius (the growers fill it)
_MAX_GROWTH = 1.15  # largest radius factor of a growing bubble


@dataclasses.dataclass(frozen=True)
class FoamState:
    """The bubbles that exist at one time (anywhere in the column).

    Attributes
    ----------
    time : float
        Subscans.
    ids : (m,) int
    centres, axes : (m, 3) float
        mm.
    rotations : (m, 3, 3) float
    fraction_in_fov : (m,) float
        Exact fraction of each bubble's volume within the detector's rows.
    """

    time: float
    ids: np.ndarray
    centres: np.ndarray
    axes: np.ndarray
    rotations: np.ndarray
    fraction_in_fov: np.ndarray

    @property
    def visible(self):
        """(m,) bool: reaching into the detector's rows."""
        return self.fraction_in_fov > 0

    @property
    def volumes(self):
        """(m,) mm^3."""
        return ellipsoid_volumes(self.axes)

    def select(self, mask):
        """The state of the bubbles where ``mask`` is true."""
        m = np.asarray(mask, dtype=bool)
        return FoamState(self.time, self.ids[m], self.centres[m], self.axes[m], self.rotations[m],
                         self.fraction_in_fov[m])


@dataclasses.dataclass(frozen=True, eq=False)
class FlowingFoam:
    """A foam column that flows, coarsens and coalesces (see the module docstring).

    Attributes
    ----------
    column : ColumnPhantom
        The foam at ``t = 0``; bubble ``b`` has id ``b``.
    velocity : float
        Upward speed, mm per subscan.
    duration : float
        Subscans simulated.
    vanish_time : (n,) float
        ``t_v`` of each bubble, ``inf`` for those that do not vanish.
    growth_share : (n,) float
        Fraction of the vanished gas each bubble takes (0 for the non-growers).
    merges : tuple of dict
        ``{"parents": (i, j), "child": id, "time": t, "offset": (3,) centre - centre of i, "axes": (3,),
        "rotation": (3, 3)}`` per coalescence.
    gas_kept : float
        Fraction of the vanished gas the growers take at the end of the scan (1: conserved).
    """

    column: ColumnPhantom
    velocity: float
    duration: float
    vanish_time: np.ndarray
    growth_share: np.ndarray
    merges: tuple
    gas_kept: float

    @property
    def n_ids(self):
        """Number of bubble ids (the column's bubbles and the coalescences' children)."""
        return len(self.column.centres) + len(self.merges)

    def _volume_factor(self, t):
        """(n,) volume of each column bubble at ``t`` over its volume at 0 (0 once vanished)."""
        v0 = self.column.volumes
        tv = self.vanish_time
        shrink = np.isfinite(tv)
        left = np.ones(len(v0))
        left[shrink] = np.clip(1.0 - t / tv[shrink], 0.0, 1.0) ** 1.5
        lost = float(np.sum(v0 * (1.0 - left)))
        return left + self.growth_share * lost / v0

    def at(self, t):
        """The bubbles existing at time ``t`` (subscans), ids ascending, as a :class:`FoamState`."""
        t = float(t)
        c = self.column
        shift = np.array([0.0, 0.0, self.velocity * t])
        factor = self._volume_factor(t)
        alive = factor > 0
        centres = c.centres + shift
        axes = c.axes * np.cbrt(np.maximum(factor, 0.0))[:, None]
        ids, cs, ax, rot = [np.flatnonzero(alive)], [centres[alive]], [axes[alive]], [c.rotations[alive]]
        n = len(c.centres)
        gone = np.zeros(n, dtype=bool)
        for m in self.merges:
            if t >= m["time"]:
                gone[list(m["parents"])] = True
                ids.append(np.array([m["child"]]))
                cs.append((centres[m["parents"][0]] + m["offset"])[None])
                ax.append(np.asarray(m["axes"])[None])
                rot.append(np.asarray(m["rotation"])[None])
        keep = np.concatenate([~gone[ids[0]]] + [np.ones(1, dtype=bool)] * (len(ids) - 1))
        ids, cs, ax, rot = (np.concatenate(x)[keep] for x in (ids, cs, ax, rot))
        h = c.fov_half_height
        s = shape_matrices(ax, rot)
        frac = fraction_below(cs, s, h) - fraction_below(cs, s, -h) if len(ids) else np.zeros(0)
        return FoamState(t, ids.astype(np.int64), cs, ax, rot, frac)

    def __repr__(self):
        return (f"FlowingFoam({len(self.column.centres)} bubbles, {self.velocity / self.column.pixel_size:g} px per "
                f"subscan over {self.duration:g} subscans, {int(np.isfinite(self.vanish_time).sum())} vanishing, "
                f"{len(self.merges)} coalescences, seed={self.column.seed!r})")


def _growth_caps(centres, axes, rotations):
    """(n,) largest common radius factor of each bubble before it touches a neighbour (capped)."""
    s = shape_matrices(axes, rotations)
    bound = axes.max(axis=1)
    i, j = cKDTree(centres).query_pairs(2.0 * _MAX_GROWTH * bound.max(), output_type="ndarray").T
    near = np.linalg.norm(centres[j] - centres[i], axis=1) < _MAX_GROWTH * (bound[i] + bound[j])
    i, j = i[near], j[near]
    cap = np.full(len(centres), _MAX_GROWTH)
    if len(i):
        f = np.sqrt(contact_function(s[i], s[j], centres[j] - centres[i]))
        np.minimum.at(cap, i, f)
        np.minimum.at(cap, j, f)
    return np.maximum(cap, 1.0)


def _merged_ellipsoid(c, axes, rotations):
    """Centre, semi-axes and rotation of the ellipsoid with two ellipsoids' volume and union's second moments."""
    vol = ellipsoid_volumes(axes)
    w = vol / vol.sum()
    centre = w @ c
    cov = sum(wk * (shape_matrices(a[None], r[None])[0] / 5.0 + np.outer(ck - centre, ck - centre))
              for wk, a, r, ck in zip(w, axes, rotations, c))
    lam, vec = np.linalg.eigh(cov)
    a = np.sqrt(5.0 * np.maximum(lam, 1e-12))
    a *= np.cbrt(vol.sum() / ellipsoid_volumes(a[None])[0])
    if np.linalg.det(vec) < 0:
        vec[:, 0] = -vec[:, 0]
    return centre, a, vec


def flowing_foam(n_bubbles=150, *, seed=0, rows=128, cols=384, pixel_size=0.012, subscans=12, flow=4.0,
                 vanishing=0.12, coalescences=4, gas_fraction=0.45, gap=None, **column):
    """A random flowing, coarsening foam column (see the module docstring).

    Parameters
    ----------
    n_bubbles : int
        About this many bubbles reach into the detector's rows at any time (sets the median radius).
    seed : int
    rows, cols : int
        Detector size.
    pixel_size : float
        mm.
    subscans : int
        Duration of the scan, subscans.
    flow : float
        Upward plug flow, detector pixels per subscan (>= 0).
    vanishing : float
        Fraction of the bubbles (the smallest) that shrink to nothing during the scan, in [0, 1).
    coalescences : int
        Pairs of neighbours that merge during the scan (>= 0).
    gas_fraction : float
        Of the packing (:func:`~bubsub.core.foam.column.column_phantom`).
    gap : float, optional
        Packing film, mm (default 6 % of the median equivalent radius).
    **column
        More options of :func:`~bubsub.core.foam.column.column_phantom` (polydispersity, aspect, ...).

    Returns
    -------
    FlowingFoam

    Raises
    ------
    ValueError
        On bad parameters, or when fewer than ``coalescences`` pairs can merge without overlap.
    """
    rng_from_seed(seed)  # checks the seed
    rng = np.random.default_rng([int(seed), 41])  # the packing draws from the seed itself
    n_target, rows, cols = count("n_bubbles", n_bubbles), count("rows", rows), count("cols", cols)
    px, duration = positive("pixel_size", pixel_size), float(count("subscans", subscans))
    flow = nonneg("flow", flow)
    vanishing = fraction("vanishing", vanishing)
    if vanishing >= 1:
        raise ValueError(f"vanishing must be below 1 (some bubbles must stay), got {vanishing}")
    n_merge = count("coalescences", coalescences, minimum=0)
    spread = float(column.get("polydispersity", 0.2))
    radius = float(column.get("radius_fraction", 0.9)) * 0.5 * cols * px
    half = 0.5 * rows * px
    try:
        median = brentq(expected_visible, 1e-4 * radius, radius,
                        args=(n_target, half, np.pi * radius**2, gas_fraction, spread))
    except ValueError:
        raise ValueError(f"no bubble size gives {n_target} bubbles in the field of view; ask for more") from None
    travel = flow * px * duration
    extra = int(np.ceil(travel / px))
    n_pack = max(n_target, int(round(expected_visible(median, 0, half + 0.5 * extra * px, np.pi * radius**2,
                                                       gas_fraction, spread))))
    packed = column_phantom(n_pack, seed=int(seed), rows=rows + extra, cols=cols, pixel_size=px,
                            gas_fraction=gas_fraction, gap=_GAP * median if gap is None else gap, **column)
    down = np.array([0.0, 0.0, 0.5 * extra * px])  # the packed rows become [-h - travel, h]
    col = dataclasses.replace(packed, centres=packed.centres - down, rows=rows,
                              z_range=(packed.z_range[0] - down[2], packed.z_range[1] - down[2]))
    n = len(col.centres)
    vol = col.volumes
    r_eq = np.cbrt(vol * 3.0 / (4.0 * np.pi))
    vanish_time = np.full(n, np.inf)
    n_vanish = int(round(vanishing * n))
    small = np.argsort(vol)[:n_vanish]
    vanish_time[small] = rng.uniform(0.1, 0.9, n_vanish) * duration
    merges = _choose_merges(rng, col, vanish_time, n_merge, duration, travel / duration)
    obstacles = [(m["offset"] + col.centres[m["parents"][0]], m["axes"], m["rotation"]) for m in merges]
    caps = _growth_caps(np.concatenate([col.centres] + [o[0][None] for o in obstacles]),
                        np.concatenate([col.axes] + [o[1][None] for o in obstacles]),
                        np.concatenate([col.rotations] + [o[2][None] for o in obstacles]))[:n]
    merging = np.zeros(n, dtype=bool)
    for m in merges:
        merging[list(m["parents"])] = True
    grower = (r_eq > np.median(r_eq)) & ~np.isfinite(vanish_time) & ~merging
    capacity = np.where(grower, vol * (caps**3 - 1.0), 0.0)
    lost = float(vol[small].sum())
    share = np.zeros(n) if lost == 0 else capacity / max(capacity.sum(), lost)
    kept = 1.0 if lost == 0 else float(min(1.0, capacity.sum() / lost))
    return FlowingFoam(column=col, velocity=travel / duration, duration=duration, vanish_time=vanish_time,
                       growth_share=share, merges=tuple(merges), gas_kept=kept)


def _choose_merges(rng, col, vanish_time, n_merge, duration, velocity):
    """Coalescing pairs: nearly touching, near the rows' middle at their time, clear of every neighbour."""
    if n_merge == 0:
        return []
    c, ax, rot = col.centres, col.axes, col.rotations
    s = shape_matrices(ax, rot)
    bound = ax.max(axis=1)
    i, j = cKDTree(c).query_pairs(2.0 * bound.max(), output_type="ndarray").T
    ok = np.isfinite(vanish_time[i]) | np.isfinite(vanish_time[j])
    i, j = i[~ok], j[~ok]
    f = contact_function(s[i], s[j], c[j] - c[i])
    order = np.argsort(f)
    tree = cKDTree(c)
    h = col.fov_half_height
    used, merges = set(), []
    times = np.sort(rng.uniform(0.2, 0.8, n_merge)) * duration
    for t in times:
        for p in order:
            a, b = int(i[p]), int(j[p])
            if a in used or b in used:
                continue
            mid = 0.5 * (c[a, 2] + c[b, 2]) + velocity * t
            if abs(mid) > 0.4 * h:
                continue
            centre, axes, vec = _merged_ellipsoid(c[[a, b]], ax[[a, b]], rot[[a, b]])
            near = [k for k in tree.query_ball_point(centre, axes.max() + 1.2 * bound.max()) if k not in (a, b)]
            sm = shape_matrices(axes[None], vec[None])
            if near and np.any(contact_function(np.repeat(sm, len(near), 0), s[near], c[near] - centre) < 1.0):
                continue
            used.update((a, b))
            merges.append({"parents": (a, b), "child": len(c) + len(merges), "time": float(t),
                           "offset": centre - c[a], "axes": axes, "rotation": vec})
            break
        else:
            raise ValueError(f"found only {len(merges)} of {n_merge} coalescences that fit in the column; "
                             f"ask for fewer --coalescences or another --seed")
    return merges
