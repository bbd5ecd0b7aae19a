"""Foam dynamics from bubble tracks: growth rates and law, T1 rearrangements, disappearances, sizes over time.

Input: one :class:`Step` per time step (subscan), bubble ids kept as track ids
from step to step (what ``bubsub reconstruct4d`` writes).

* Rates: ``dV/dt`` and ``d(V^(2/3))/dt`` of each bubble at each step, by central
  differences over the nearest steps on either side where its volume is known
  (one-sided at either end of its track); bubbles cut by the field of view
  have no whole volume and no rate.
* Growth law (von Neumann-Mullins in 3D, Glazier 1993): ``d(V^(2/3))/dt = k (Z -
  Z_0)`` with ``Z`` the coordination; ``k`` and ``Z_0`` by least squares over
  every (bubble, step) with a rate, with standard errors from the residual
  variance (``Z_0 = -intercept / k``, its error by the delta method).
* T1 events between two consecutive steps: bubbles ``a, b`` that were in
  contact and are not any more, and ``c, d`` that were not and are now, where
  ``c`` and ``d`` were both neighbours of ``a`` and of ``b`` before, and ``a`` and ``b``
  are both neighbours of ``c`` and of ``d`` after (the neighbour swap of the four
  bubbles), all four present at both steps.
* Disappearances: a bubble present at a step and not at the next; a
  coalescence when one of its neighbours gained at least half its volume
  (the neighbour that gained most is named), else a disappearance (shrunk
  away by coarsening, or left the field of view). Appearances: the reverse.
  Where the reconstruction recorded its tracks' lineage (``lineage.csv`` of
  ``bubsub reconstruct4d``: births, ends, coalescences with their parents and
  child), the events between two steps are taken from it, and guessed from
  the volumes only for the bubbles it does not name.
* Sizes: count, mean, median, standard deviation and Sauter mean
  (``sum r^3 / sum r^2``) of the equivalent radii per step, and their
  distribution over bins shared by all steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bubsub.core.projection.mesh import equivalent_radius

__all__ = ["Step", "growth_rates", "fit_growth_law", "t1_events", "track_events", "size_tables"]


@dataclass(frozen=True)
class Step:
    """The bubbles of one time step.

    Attributes
    ----------
    index : int
        Subscan index.
    time : float
        Mid-time (s, or the subscan index).
    ids : (n,) int
        Track ids.
    volume : (n,) float
        mm^3; NaN for bubbles cut by the field of view.
    coordination : (n,) int
    centroid : (n, 3) float
        mm.
    pairs : frozenset of (int, int)
        Contacts as ``(smaller id, larger id)``.
    """

    index: int
    time: float
    ids: np.ndarray
    volume: np.ndarray
    coordination: np.ndarray
    centroid: np.ndarray
    pairs: frozenset

    def lookup(self):
        """``{id: row index}``."""
        return {int(i): k for k, i in enumerate(self.ids)}

    def neighbours(self):
        """``{id: set of ids in contact}``."""
        out = {int(i): set() for i in self.ids}
        for a, b in self.pairs:
            out.setdefault(a, set()).add(b)
            out.setdefault(b, set()).add(a)
        return out


def _ordered(steps):
    steps = sorted(steps, key=lambda s: s.time)
    t = [s.time for s in steps]
    if len(set(t)) != len(t):
        raise ValueError("two time steps have the same time; rates need distinct times")
    return steps


def _nearest_known(steps, maps, k, bid, step):
    """``(time, volume)`` of bubble ``bid`` at the nearest step before (``step=-1``) or after (``1``) step ``k``
    where its whole volume is known, or None."""
    j = k + step
    while 0 <= j < len(steps):
        if bid in maps[j]:
            w = steps[j].volume[maps[j][bid]]
            if np.isfinite(w):
                return steps[j].time, w
        j += step
    return None


def growth_rates(steps):
    """Per bubble and step: volume, coordination, ``dV/dt`` and ``d(V^(2/3))/dt``.

    Returns
    -------
    list of dict
        ``subscan, time, bubble_id, volume, coordination, volume_rate, two_thirds_rate`` (rates NaN
        where the bubble's volume is known at no other step).
    """
    steps = _ordered(steps)
    maps = [s.lookup() for s in steps]
    rows = []
    for k, s in enumerate(steps):
        for r, bid in enumerate(s.ids):
            v = s.volume[r]
            if not np.isfinite(v):
                continue

            before, after = _nearest_known(steps, maps, k, int(bid), -1), _nearest_known(steps, maps, k, int(bid), 1)
            ends = [p for p in (before, after) if p is not None]
            if len(ends) == 2:
                (t0, v0), (t1, v1) = before, after
            elif ends:
                (t0, v0), (t1, v1) = sorted([(s.time, v), ends[0]])
            else:
                t0 = t1 = v0 = v1 = None
            if t0 is None:
                dv = dv23 = float("nan")
            else:
                dv = (v1 - v0) / (t1 - t0)
                dv23 = (v1 ** (2 / 3) - v0 ** (2 / 3)) / (t1 - t0)
            rows.append({"subscan": s.index, "time": s.time, "bubble_id": int(bid), "volume": float(v),
                         "coordination": int(s.coordination[r]), "volume_rate": float(dv),
                         "two_thirds_rate": float(dv23)})
    return rows


def fit_growth_law(coordination, rate):
    """Least-squares fit of ``rate = k (Z - Z_0)``.

    Parameters
    ----------
    coordination : (n,) float
        ``Z``.
    rate : (n,) float
        ``d(V^(2/3))/dt``, mm^2 per time unit.

    Returns
    -------
    dict
        ``points``, ``slope`` ``k`` and ``slope_stderr``, ``intercept`` and its error, ``z0`` and
        ``z0_stderr``, ``r2``; the estimates are None (with a ``reason``) when there are fewer than
        three points or the coordination does not vary.
    """
    z = np.asarray(coordination, dtype=float)
    y = np.asarray(rate, dtype=float)
    ok = np.isfinite(z) & np.isfinite(y)
    z, y = z[ok], y[ok]
    out = {"points": int(len(z)), "slope": None, "slope_stderr": None, "intercept": None, "intercept_stderr": None,
           "z0": None, "z0_stderr": None, "r2": None}
    if len(z) < 3 or np.ptp(z) == 0:
        out["reason"] = "fewer than three rates" if len(z) < 3 else "every bubble has the same coordination"
        return out
    X = np.stack([z, np.ones_like(z)], axis=1)
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    resid = y - X @ coef
    dof = len(z) - 2
    s2 = float(resid @ resid) / dof if dof > 0 else float("nan")
    cov = s2 * np.linalg.inv(X.T @ X)
    k, b = float(coef[0]), float(coef[1])
    out.update(slope=k, slope_stderr=float(np.sqrt(cov[0, 0])), intercept=b, intercept_stderr=float(np.sqrt(cov[1, 1])))
    ss = float(((y - y.mean()) ** 2).sum())
    out["r2"] = float(1 - (resid @ resid) / ss) if ss > 0 else None
    if k != 0:
        z0 = -b / k
        # Z_0 = -b / k: its gradient over (k, b) is (b / k^2, -1 / k) = -(Z_0, 1) / k
        g = -np.array([z0, 1.0]) / k
        out.update(z0=float(z0), z0_stderr=float(np.sqrt(g @ cov @ g)))
    return out


def t1_events(steps):
    """T1 neighbour swaps between consecutive steps (see the module docstring).

    Returns
    -------
    list of dict
        ``subscan_before, subscan_after, time_before, time_after, lost_a, lost_b, gained_c, gained_d, x, y, z``
        (position: the mean centroid of the four bubbles over both steps).
    """
    steps = _ordered(steps)
    rows = []
    for s0, s1 in zip(steps[:-1], steps[1:]):
        both = set(map(int, s0.ids)) & set(map(int, s1.ids))
        n0, n1 = s0.neighbours(), s1.neighbours()
        lost = sorted(p for p in s0.pairs - s1.pairs if p[0] in both and p[1] in both)
        gained = sorted(p for p in s1.pairs - s0.pairs if p[0] in both and p[1] in both)
        m0, m1 = s0.lookup(), s1.lookup()
        for a, b in lost:
            common = n0[a] & n0[b]
            for c, d in gained:
                if c in common and d in common and {a, b} <= (n1[c] & n1[d]):
                    quad = (a, b, c, d)
                    pos = np.mean([s0.centroid[m0[q]] for q in quad] + [s1.centroid[m1[q]] for q in quad], axis=0)
                    rows.append({"subscan_before": s0.index, "subscan_after": s1.index, "time_before": s0.time,
                                 "time_after": s1.time, "lost_a": a, "lost_b": b, "gained_c": c, "gained_d": d,
                                 "x": float(pos[0]), "y": float(pos[1]), "z": float(pos[2])})
    return rows


def _recorded(lineage, before, after):
    """What ``lineage`` records between subscans ``before`` and ``after``: ``{gone id: (kind, partner)}`` and
    the ids that begin there (births, and coalescences' children, which are no appearance)."""
    gone, begun = {}, {}
    for row in lineage or ():
        if int(row["subscan_before"]) != before or str(row["subscan"]) != str(after):
            continue
        parents = [int(i) for i in str(row["parent_ids"]).split(";") if i != ""]
        children = [int(i) for i in str(row["child_ids"]).split(";") if i != ""]
        if row["event"] == "coalescence":
            for a in parents:
                gone[a] = ("coalescence", children[0] if len(children) == 1 else None)
            begun.update({c: "coalescence" for c in children})
        elif row["event"] == "end":
            gone.update({a: ("disappearance", None) for a in parents})
        elif row["event"] == "birth":
            begun.update({c: "appearance" for c in children})
    return gone, begun


def track_events(steps, lineage=None):
    """Disappearances, coalescences and appearances between consecutive steps.

    Parameters
    ----------
    steps : sequence of Step
    lineage : sequence of dict, optional
        Rows of ``lineage.csv`` (``event``: birth, end or coalescence; ``subscan_before``, ``subscan``,
        ``parent_ids``, ``child_ids``: ids separated by semicolons). The bubbles it names between two steps
        take its events (a coalescence's partner is the merged bubble); the others are guessed from the volumes.

    Returns
    -------
    list of dict
        ``subscan_before, subscan_after, time_before, time_after, kind, bubble_id, partner_id (or None),
        volume, x, y, z`` (volume and position at the step where the bubble exists).
    """
    steps = _ordered(steps)
    rows = []
    for s0, s1 in zip(steps[:-1], steps[1:]):
        m0, m1 = s0.lookup(), s1.lookup()
        n0 = s0.neighbours()
        base = {"subscan_before": s0.index, "subscan_after": s1.index, "time_before": s0.time, "time_after": s1.time}
        gone, begun = _recorded(lineage, s0.index, s1.index)
        for a in sorted(set(m0) - set(m1)):
            va = s0.volume[m0[a]]
            c = s0.centroid[m0[a]]
            if a in gone:
                kind, partner = gone[a]
                rows.append({**base, "kind": kind, "bubble_id": a, "partner_id": partner, "volume": float(va),
                             "x": float(c[0]), "y": float(c[1]), "z": float(c[2])})
                continue
            best, gain = None, -np.inf
            for b in sorted(n0.get(a, ())):
                if b in m1:
                    g = s1.volume[m1[b]] - s0.volume[m0[b]]
                    if np.isfinite(g) and g > gain:
                        best, gain = b, g
            merged = best is not None and np.isfinite(va) and gain >= 0.5 * va
            c = s0.centroid[m0[a]]
            rows.append({**base, "kind": "coalescence" if merged else "disappearance", "bubble_id": a,
                         "partner_id": best if merged else None, "volume": float(va),
                         "x": float(c[0]), "y": float(c[1]), "z": float(c[2])})
        for a in sorted(set(m1) - set(m0)):
            if begun.get(a) == "coalescence":
                continue
            c = s1.centroid[m1[a]]
            rows.append({**base, "kind": "appearance", "bubble_id": a, "partner_id": None,
                         "volume": float(s1.volume[m1[a]]), "x": float(c[0]), "y": float(c[1]), "z": float(c[2])})
    return rows


def _radii(step):
    v = step.volume[np.isfinite(step.volume)]
    return equivalent_radius(v, 3)


def size_tables(steps, bins=None):
    """Size statistics per step and the size distribution over shared bins.

    Parameters
    ----------
    steps : sequence of Step
    bins : int or sequence of float, optional
        Bin count or edges (mm) of the equivalent radius; default numpy's ``"auto"`` rule on all
        steps together, at most 30 bins.

    Returns
    -------
    sizes : list of dict
        ``subscan, time, bubbles, bubbles_whole, mean_radius, median_radius, std_radius, sauter_radius,
        gas_volume`` (of the whole bubbles).
    distribution : list of dict
        ``subscan, time, r_lo, r_hi, bubbles, fraction``.
    """
    steps = _ordered(steps)
    radii = [_radii(s) for s in steps]
    every = np.concatenate(radii) if radii else np.zeros(0)
    sizes = []
    for s, r in zip(steps, radii):
        sizes.append({"subscan": s.index, "time": s.time, "bubbles": int(len(s.ids)), "bubbles_whole": int(len(r)),
                      "mean_radius": float(r.mean()) if len(r) else float("nan"),
                      "median_radius": float(np.median(r)) if len(r) else float("nan"),
                      "std_radius": float(r.std()) if len(r) else float("nan"),
                      "sauter_radius": float((r ** 3).sum() / (r ** 2).sum()) if len(r) else float("nan"),
                      "gas_volume": float(np.nansum(s.volume))})
    if not len(every):
        return sizes, []
    if bins is None:
        edges = np.histogram_bin_edges(every, bins="auto")
        if len(edges) > 31:
            edges = np.linspace(every.min(), every.max(), 31)
    else:
        edges = np.histogram_bin_edges(every, bins=bins)
    distribution = []
    for s, r in zip(steps, radii):
        counts, _ = np.histogram(r, bins=edges)
        for lo, hi, c in zip(edges[:-1], edges[1:], counts):
            distribution.append({"subscan": s.index, "time": s.time, "r_lo": float(lo), "r_hi": float(hi),
                                 "bubbles": int(c), "fraction": float(c / len(r)) if len(r) else float("nan")})
    return sizes, distribution
