"""The scores of ``bubsub bench dynamic`` (:mod:`bubsub.bench.dynamic`): a route's labels per subscan against
the flowing foam's truth, and what the truth alone says each order of a chain must find anew.

Each subscan is scored against the truth at its mid-time inside the field of
view, on the evaluation grid (``phantom.json``: two pixels per voxel), with
:func:`bubsub.bench.matching.match`:

* **true**: truth bubbles with a voxel in view; **found**: the reconstructed
  bubble overlapping it most has IoU >= 0.5 with it, and it is not merged;
  **merged**: one reconstructed bubble covers more than 30 % of it and of
  another truth bubble; **missed**: the rest; **spurious**: reconstructed
  bubbles in view that are no truth bubble's best match; **DDI** of the gas
  masks in view;
* **anew**: the truth bubbles that exist at subscan ``k`` but not at ``k + 1``
  (they leave through the top, vanish or coalesce later): a backward chain
  cannot carry them from its successor and must find them anew at ``k``;
  counted all and those whose visible part holds a ball of at least 6 pixels'
  radius (``anew6``);
* **small**: truth bubbles whose visible part holds a largest ball of 6 to 12
  pixels' radius (inside the foam or as a cap at the detector's edge);
* **coalescences** (:func:`score_coalescences`): per true coalescence, its
  parents found in the subscan before, its child found in the subscan after,
  and the route's ``lineage.csv`` row for it; lineage coalescence rows that
  match none are false;
* **track purity**: each reconstructed row (a track's bubble in a subscan) is
  put on the truth bubble it overlaps most; a track's purity is the share of
  its rows on its most frequent truth bubble, and the run's is the sum over
  tracks of those rows over all rows (rows on no truth bubble are impure).

The largest ball a visible part holds is the smallest semi-axis for a bubble
wholly in view, and for one cut by the top or bottom row the maximum of the
distance transform of its part between the cut planes on a one-pixel grid.

:func:`chain_burden` counts, from the truth alone, the bubbles a backward and a forward chain must find
anew, with the reason for each.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
from scipy import ndimage

from bubsub.bench.matching import MIN_IOU, match, overlaps, truth_labels

__all__ = ["MERGE_COVER", "SMALL_BALL", "flowing_truth", "visible_ball", "truth_subscan", "row_owners",
           "track_purity", "score_subscan", "score_run", "score_coalescences", "read_lineage", "chain_burden"]

#: A reconstructed bubble covering more than this share of two truth bubbles merges them.
MERGE_COVER = 0.3
#: The small bubbles: the largest ball their visible part holds, pixels.
SMALL_BALL = (6.0, 12.0)

def flowing_truth(sim_dir):
    """``(meta, tables, events)`` of a flowing foam's simulation folder.

    Returns
    -------
    meta : dict
        ``phantom.json``.
    tables : list of dict
        Per subscan, ``truth/subscan_kkkk.csv`` as ``{column: (n,) float array}``.
    events : list of dict
        ``events.csv`` rows.
    """
    sim_dir = Path(sim_dir)
    meta = json.loads((sim_dir / "phantom.json").read_text())
    if meta.get("phantom") != "flowing3d":
        raise ValueError(f"{sim_dir} is not a flowing foam (make one with bubsub simulate --phantom flowing3d)")
    tables = []
    for k in range(meta["subscans"]):
        with open(sim_dir / meta["truth_table"].format(k=k), newline="") as fh:
            rows = list(csv.DictReader(fh))
        tables.append({c: np.array([float(r[c]) for r in rows]) for c in (rows[0] if rows else {"id": ()})})
    with open(sim_dir / meta["events"], newline="") as fh:
        events = list(csv.DictReader(fh))
    return meta, tables, events


def _ellipsoids(table):
    centres = np.stack([table[f"centre_{a}_mm"] for a in "xyz"], axis=1)
    axes = np.stack([table[f"semi_axis_{k}_mm"] for k in (1, 2, 3)], axis=1)
    rot = np.stack([table[f"rotation_{i}{j}"] for i in (1, 2, 3) for j in (1, 2, 3)], axis=1).reshape(-1, 3, 3)
    return centres, axes, rot


def visible_ball(table, meta):
    """(n,) radius of the largest ball within each truth bubble's visible part, pixels.

    The smallest semi-axis for a bubble wholly between the detector's top and
    bottom planes; for a cut one, the maximum of the Euclidean distance
    transform of its part between the planes, sampled on a one-pixel grid.
    """
    c = meta["column"]
    px, h = c["pixel_size_mm"], c["fov_half_height_mm"]
    if not len(table.get("id", ())):
        return np.zeros(0)
    centres, axes, rot = _ellipsoids(table)
    out = axes.min(axis=1) / px
    cut = (table["cut_top"] > 0) | (table["cut_bottom"] > 0)
    for b in np.flatnonzero(cut):
        reach = axes[b].max() + px
        z0, z1 = max(centres[b, 2] - reach, -h), min(centres[b, 2] + reach, h)
        if z1 <= z0:
            out[b] = 0.0
            continue
        grid = [np.arange(centres[b, i] - reach, centres[b, i] + reach, px) for i in (0, 1)]
        grid.append(np.arange(z0 + px / 2, z1, px))
        pts = np.stack(np.meshgrid(*grid, indexing="ij"), axis=-1) - centres[b]
        inside = np.sum((pts @ rot[b] / axes[b]) ** 2, axis=-1) <= 1.0
        out[b] = float(ndimage.distance_transform_edt(np.pad(inside, 1)).max()) if inside.any() else 0.0
    return out


def truth_subscan(meta, table):
    """Truth labels of one subscan on the evaluation grid (row index + 1, 0 outside the field of view) and the ids."""
    if not len(table.get("id", ())):
        return np.zeros(tuple(meta["grid_shape"]), np.int32), np.zeros(0, np.int64)
    return truth_labels(meta, table), table["id"].astype(np.int64)


def row_owners(truth, rec):
    """(n_rec,) the truth label each reconstructed label ``1..n_rec`` overlaps most (0: none)."""
    table, _, n_r = overlaps(truth, rec)
    shared = table[1:, :]
    owner = np.argmax(shared, axis=0) + 1
    owner[shared.max(axis=0, initial=0) == 0] = 0
    return owner[1:len(n_r)]


def track_purity(rows):
    """Share of a run's rows that lie on their track's most frequent truth bubble.

    Parameters
    ----------
    rows : iterable of (track id, truth id or -1)
        One per reconstructed bubble per subscan.

    Returns
    -------
    (purity, tracks, rows) : (float or None, int, int)
    """
    by_track = {}
    for track, truth in rows:
        by_track.setdefault(track, []).append(truth)
    n = sum(len(v) for v in by_track.values())
    pure = 0
    for v in by_track.values():
        real = [t for t in v if t >= 0]
        pure += max(np.unique(real, return_counts=True)[1]) if real else 0
    return (float(pure / n) if n else None), len(by_track), n


def score_subscan(truth, truth_ids, rec, ball, anew, anew_forward=()):
    """The scores of one subscan (see the module docstring).

    Parameters
    ----------
    truth, rec : int ndarray
        Labels on the evaluation grid, 0 outside the field of view.
    truth_ids : (n_truth,) int
        Bubble id of truth label ``i + 1``.
    ball : (n_truth,) float
        :func:`visible_ball`, pixels.
    anew : set of int
        Truth ids a backward chain must find anew here.
    anew_forward : set of int
        Truth ids a forward chain must find anew here (not in view in the previous subscan).

    Returns
    -------
    dict
        ``truth, found, missed, merged, spurious, reconstructed, ddi`` of
        :func:`~bubsub.bench.matching.match` and ``anew, anew_found, anew6, anew6_found, small, small_found``,
        ``fwd, fwd_found, fwd6, fwd6_found`` for ``anew_forward``, and ``truth6, found6``: the truth bubbles whose
        visible part holds a ball of at least 6 pixels' radius and how many of them are found.
    """
    return _score_subscan(truth, truth_ids, rec, ball, anew, anew_forward)[0]


def _score_subscan(truth, truth_ids, rec, ball, anew, anew_forward):
    """:func:`score_subscan`'s dict and the set of truth ids found."""
    m = match(truth, rec)  # spurious, DDI, and each truth bubble's best reconstructed bubble and its IoU
    table, n_t, _ = overlaps(truth, rec)
    covers = table[:, 1:] > MERGE_COVER * np.maximum(n_t, 1)[:, None]
    covers[0] = False
    merged = (covers & (covers.sum(axis=0) > 1)[None, :]).any(axis=1)
    status = {i: "merged" if merged[i] else ("found" if iou >= MIN_IOU else "missed")
              for i, _, iou, _ in m["per_truth"]}
    found = {int(truth_ids[i - 1]) for i, st in status.items() if st == "found"}
    present = {int(truth_ids[i - 1]): i - 1 for i in status}
    out = {k: m[k] for k in ("truth", "spurious", "reconstructed", "ddi")}
    out.update({k: sum(st == k for st in status.values()) for k in ("found", "missed", "merged")})
    small = [b for b, i in present.items() if SMALL_BALL[0] <= ball[i] <= SMALL_BALL[1]]
    big = [b for b, i in present.items() if ball[i] >= SMALL_BALL[0]]
    out.update(small=len(small), small_found=sum(b in found for b in small), truth6=len(big),
               found6=sum(b in found for b in big))
    for name, ids in (("anew", anew), ("fwd", anew_forward)):
        a = [b for b in ids if b in present]
        a6 = [b for b in a if ball[present[b]] >= SMALL_BALL[0]]
        out.update({name: len(a), f"{name}_found": sum(b in found for b in a), f"{name}6": len(a6),
                    f"{name}6_found": sum(b in found for b in a6)})
    return out, found


def score_run(meta, tables, labels_of, subscans=None, *, events=None, lineage=None):
    """Score every subscan of a run and its tracks.

    Parameters
    ----------
    meta, tables
        :func:`flowing_truth`.
    labels_of : callable
        ``k -> (labels, track ids)`` of the route's subscan ``k`` (labels on the evaluation grid, 0 outside the
        field of view; ``ids[j]`` the track of label ``j + 1``), or None when the route has no subscan ``k``.
    subscans : iterable of int, optional
        Default all.
    events : list of dict, optional
        ``events.csv`` rows (:func:`flowing_truth`): with them, ``totals["coalescences"]`` scores each true
        coalescence (:func:`score_coalescences`).
    lineage : list of dict, optional
        The route's ``lineage.csv`` rows (None: the route keeps no lineage).

    Returns
    -------
    dict
        ``subscans`` (per subscan :func:`score_subscan` with ``subscan``), ``totals`` (sums, ``found_share``,
        ``mean_ddi``, ``track_purity``, ``tracks``, ``rows``, and ``coalescences`` when ``events`` are given).
    """
    per, rows, found_at, owner_at = [], [], {}, {}
    ks = list(range(meta["subscans"]) if subscans is None else subscans)
    ids_at = [set(t["id"].astype(int).tolist()) if len(t.get("id", ())) else set() for t in tables]
    for k in ks:
        got = labels_of(k)
        if got is None:
            continue
        rec, rec_ids = got
        truth, truth_ids = truth_subscan(meta, tables[k])
        anew = ids_at[k] - ids_at[k + 1] if k + 1 < len(tables) else set()
        fwd = ids_at[k] - ids_at[k - 1] if k > 0 else set()
        s, found_at[k] = _score_subscan(truth, truth_ids, rec, visible_ball(tables[k], meta), anew, fwd)
        per.append({"subscan": k, **s})
        owners = row_owners(truth, rec)
        present = np.flatnonzero(np.bincount(rec.ravel(), minlength=len(rec_ids) + 1)[1:] > 0)
        here = [(int(rec_ids[j]), int(truth_ids[owners[j] - 1]) if owners[j] else -1) for j in present]
        owner_at[k] = dict(here)
        rows += here
    purity, n_tracks, n_rows = track_purity(rows)
    keys = ("truth", "found", "missed", "merged", "spurious", "anew", "anew_found", "anew6", "anew6_found",
            "fwd", "fwd_found", "fwd6", "fwd6_found", "truth6", "found6",
            "small", "small_found")
    totals = {k: int(sum(p[k] for p in per)) for k in keys}
    totals.update(found_share=totals["found"] / totals["truth"] if totals["truth"] else None,
                  mean_ddi=float(np.mean([p["ddi"] for p in per])) if per else None,
                  track_purity=purity, tracks=n_tracks, rows=n_rows)
    if events is not None:
        totals["coalescences"] = score_coalescences(events, found_at, owner_at, lineage)
    return {"subscans": per, "totals": totals}


def score_coalescences(events, found_at, owner_at, lineage=None):
    """How a route shows the simulation's coalescences, and the lineage's coalescence rows that are none.

    A true coalescence (``events.csv``: ``coalesce``, its child ``id``, its ``parents``, ``subscan`` the first
    subscan whose truth shows the child) is scored where the route has both the subscan before it and
    ``subscan``:

    * **two before**: both parents found (:func:`score_subscan`) in the subscan before;
    * **one after**: the child found in ``subscan``;
    * **in the lineage**: a ``coalescence`` row of ``lineage.csv`` between the same two subscans whose parent
      tracks lie on the true parents and whose child track on the true child (each reconstructed bubble put on
      the truth bubble it overlaps most, :func:`row_owners`).

    A lineage coalescence row that is no true coalescence's is **false** (a swollen neighbour or a cap beside a
    cut neighbour taken for one, or a true one put between other subscans). A row that names a true
    coalescence's tracks one subscan early or late (a coalescence during a subscan's acquisition: its data show
    two bubbles part of the time) is counted apart too (``..._a_subscan_off``): its parent tracks lie on the
    true parents at the earlier of the two subscans before, its child track on the true child at the later of
    the two after.

    Parameters
    ----------
    events : list of dict
        ``events.csv`` rows.
    found_at : dict
        ``subscan -> set`` of the truth ids found there.
    owner_at : dict
        ``subscan -> {track id: truth id (-1: none)}`` of the route's bubbles there.
    lineage : list of dict, optional
        ``lineage.csv`` rows (any events; only ``coalescence`` rows count); None: the route has no lineage.

    Returns
    -------
    dict
        ``events`` (scored), ``two_before``, ``one_after``; ``in_lineage``, ``in_lineage_a_subscan_off`` (the
        events not in the lineage that a row names a subscan off), ``rows``, ``false_rows``,
        ``false_rows_a_subscan_off`` (of the false rows; these None without a lineage); ``per_event``
        (``child``, ``parents``, ``subscan``, ``two_before``, ``one_after``, ``in_lineage``,
        ``in_lineage_a_subscan_off``).
    """
    true = []
    for e in events:
        k = int(e["subscan"])
        if e["event"] == "coalesce" and k - 1 in found_at and k in found_at:
            true.append((k - 1, k, frozenset(int(p) for p in e["parents"].split(";")), int(e["id"])))
    rows = [r for r in (lineage or []) if r.get("event") == "coalescence"]

    def owners(k, ids):
        return [owner_at.get(k, {}).get(int(i), -1) for i in str(ids).split(";") if str(i).strip()]

    def matches(row, ev, off=(0,)):
        """Whether ``row`` names ``ev``'s tracks between its subscans shifted by one of ``off``: the parent
        tracks on the parents at the earlier of the two subscans before, the child track on the child at the
        later of the two after."""
        before, after, parents, child = ev
        try:
            rb, ra = int(row["subscan_before"]), int(row["subscan"])
        except ValueError:
            return False
        if (rb - before, ra - after) not in {(d, d) for d in off}:
            return False
        p = owners(min(rb, before), row["parent_ids"])
        return (len(p) == len(set(p)) == len(parents) and set(p) == parents
                and owners(max(ra, after), row["child_ids"]) == [child])

    per = []
    for ev in true:
        before, after, parents, child = ev
        per.append({"child": child, "parents": sorted(parents), "subscan": after,
                    "two_before": parents <= found_at[before], "one_after": child in found_at[after],
                    "in_lineage": None if lineage is None else any(matches(r, ev) for r in rows),
                    "in_lineage_a_subscan_off": None if lineage is None else
                    any(matches(r, ev, (-1, 1)) for r in rows)})
    false = [r for r in rows if not any(matches(r, ev) for ev in true)]
    return {"events": len(per), "two_before": sum(p["two_before"] for p in per),
            "one_after": sum(p["one_after"] for p in per),
            "in_lineage": None if lineage is None else sum(p["in_lineage"] for p in per),
            "in_lineage_a_subscan_off": None if lineage is None else
            sum(p["in_lineage_a_subscan_off"] and not p["in_lineage"] for p in per),
            "rows": None if lineage is None else len(rows),
            "false_rows": None if lineage is None else len(false),
            "false_rows_a_subscan_off": None if lineage is None else
            sum(any(matches(r, ev, (-1, 1)) for ev in true) for r in false),
            "per_event": per}


def read_lineage(rec_dir):
    """The rows of a ``reconstruct4d`` folder's ``lineage.csv`` (dicts of strings), or None when it has none."""
    path = Path(rec_dir) / "lineage.csv"
    if not path.is_file():
        return None
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def chain_burden(meta, tables, events):
    """What each order of a chain must find anew, from the truth alone.

    A backward chain must find anew at ``k`` the bubbles in view at ``k`` but not
    at ``k + 1`` (they leave through the top, vanish or coalesce later); a
    forward chain those in view at ``k`` but not at ``k - 1`` (they entered
    through the bottom or were born by a coalescence).

    Returns
    -------
    dict
        ``{"backward" | "forward": {"all": n, "ball6": n with a visible ball >= 6 px, "reasons": {reason: n}}}``.
    """
    ids_at = [t["id"].astype(int).tolist() if len(t.get("id", ())) else [] for t in tables]
    balls = [dict(zip(ids, visible_ball(t, meta))) for ids, t in zip(ids_at, tables)]
    why = {}
    for e in events:
        k, b = int(e["subscan"]), int(e["id"])
        if e["event"] == "coalesce":
            why[("forward", k, b)] = "coalescence child"
            for p in e["parents"].split(";"):
                why[("backward", k, int(p))] = "coalesce later"
        else:
            d = "forward" if e["event"] == "enter" else "backward"
            why[(d, k, b)] = {"enter": "entered through the bottom", "exit": "leave through the top later",
                              "vanish": "vanish later"}[e["event"]]
    out = {}
    for d, step in (("backward", 1), ("forward", -1)):
        res = {"all": 0, "ball6": 0, "reasons": {}}
        for k in range(len(tables)):
            if not 0 <= k + step < len(tables):
                continue
            for b in set(ids_at[k]) - set(ids_at[k + step]):
                reason = why.get((d, k + max(step, 0), b), "other")
                res["all"] += 1
                res["ball6"] += int(balls[k][b] >= SMALL_BALL[0])
                res["reasons"][reason] = res["reasons"].get(reason, 0) + 1
        out[d] = res
    return out
