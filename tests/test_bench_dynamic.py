"""The dynamic benchmark's scores, on a tiny flowing foam and reconstructions made from its own truth."""


import csv

import numpy as np
import pytest

from bubsub.bench import dynamic as D
from bubsub.bench import dynamic_scores as S
from bubsub.core.foam.ellipsoids import ellipsoid_mesh
from bubsub.core.io.meshio import read_ply, write_ply
from bubsub.core.projection.mesh import Mesh


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    from bubsub.clients.cli.main import main

    out = tmp_path_factory.mktemp("flow") / "sim"
    assert main(["simulate", "--phantom", "flowing3d", "--det-count", "96", "--bubbles", "30", "--subscans", "3",
                 "--projections-per-subscan", "8", "--coalescences", "1", "--seed", "1", "--out", str(out)]) == 0
    return out


def _fake_run(sim, folder, edit=None):
    """A reconstruct4d-like folder whose bubbles are the truth meshes (``edit(k, meshes, ids)`` may change them)."""
    for k in range(3):
        meshes, ids = read_ply(sim / "truth" / f"subscan_{k:04d}.ply", with_ids=True)
        if edit:
            meshes, ids = edit(k, list(meshes), list(ids))
        (folder / f"subscan_{k:04d}").mkdir(parents=True)
        write_ply(folder / f"subscan_{k:04d}" / "bubbles.ply", meshes, ids)
    return folder


def test_the_truth_itself_scores_perfectly_and_anew_follows_the_events(sim, tmp_path):
    meta, tables, events = S.flowing_truth(sim)
    s = S.score_run(meta, tables, D.bubsub_labels(_fake_run(sim, tmp_path / "rec"), meta))
    t = s["totals"]
    assert t["found"] == t["truth"] > 0 and t["merged"] == t["spurious"] == t["missed"] == 0
    assert t["track_purity"] == 1.0 and t["mean_ddi"] < 0.01
    # anew at k: in view at k, gone at k + 1 by an exit, a vanishing or a coalescence (events.csv, independent)
    for p in s["subscans"][:-1]:
        k = p["subscan"]
        labels, ids = S.truth_subscan(meta, tables[k])
        at_k = set(ids[np.unique(labels[labels > 0]) - 1].tolist())  # with a voxel in view on the grid
        gone = {int(e["id"]) for e in events if int(e["subscan"]) == k + 1 and e["event"] in ("exit", "vanish")}
        gone |= {int(x) for e in events if int(e["subscan"]) == k + 1 and e["event"] == "coalesce"
                 for x in e["parents"].split(";")}
        assert p["anew"] == len(gone & at_k) == p["anew_found"]
    assert s["subscans"][-1]["anew"] == 0


def test_a_bubble_over_two_true_ones_merges_both_and_swapped_ids_lower_purity(sim, tmp_path):
    meta, tables, _ = S.flowing_truth(sim)
    tab = tables[1]
    centres = np.stack([tab[f"centre_{a}_mm"] for a in "xyz"], axis=1)
    inner = np.flatnonzero((np.abs(centres[:, 2]) < 0.3) & (tab["cut_top"] == 0) & (tab["cut_bottom"] == 0))
    d = np.linalg.norm(centres[inner, None] - centres[None, inner], axis=2) + 1e9 * np.eye(len(inner))
    a, b = (inner[i] for i in np.unravel_index(np.argmin(d), d.shape))
    ida, idb = int(tab["id"][a]), int(tab["id"][b])
    mid = 0.5 * (centres[a] + centres[b])
    later = set(tables[2]["id"].astype(int))
    swap = [int(i) for i, c in zip(tab["id"], centres) if int(i) in later and np.linalg.norm(c - mid) > 1.0][:2]
    assert len(swap) == 2

    def edit(k, meshes, ids):
        if k == 1:  # one ellipsoid covering both neighbours replaces them
            big = ellipsoid_mesh(mid, [0.6 * d.min() + 0.3] * 3, np.eye(3), -0.1, 3)
            keep = [i for i, x in enumerate(ids) if x not in (ida, idb)]
            return [meshes[i] for i in keep] + [big], [ids[i] for i in keep] + [10_000]
        if k == 2:  # two tracks swap their ids in one subscan
            ids = [swap[1] if x == swap[0] else swap[0] if x == swap[1] else x for x in ids]
        return meshes, ids

    s = S.score_run(meta, tables, D.bubsub_labels(_fake_run(sim, tmp_path / "rec", edit), meta))
    p = s["subscans"][1]
    assert p["merged"] >= 2 and p["found"] == p["truth"] - p["merged"]
    # each swapped track has one of its rows (the last subscan's) on another truth bubble
    rows = s["totals"]["rows"]
    assert s["totals"]["track_purity"] == pytest.approx((rows - 2) / rows)


def test_track_purity_and_overlap_links():
    assert S.track_purity([(1, 5), (1, 5), (1, 6), (2, 7), (2, -1)]) == (3 / 5, 2, 5)
    a = np.zeros((1, 10, 10), np.int32)
    a[0, 1:4, 1:4], a[0, 6:9, 6:9] = 1, 2
    b = np.zeros_like(a)
    b[0, 2:5, 1:4], b[0, 0:2, 7:9] = 2, 1  # label 2 continues label 1 shifted a row; label 1 is new
    ids, nxt = D.link_by_overlap(a, np.array([40, 41]), b, 50)
    assert ids.tolist() == [50, 40] and nxt == 51


def test_visible_ball_is_the_axis_or_the_cut_part_ball(sim):
    meta, tables, _ = S.flowing_truth(sim)
    px, h = meta["column"]["pixel_size_mm"], meta["column"]["fov_half_height_mm"]
    # a ball of 10 px whose centre lies 4 px below the top row: its visible part holds a ball of (10 + 4) / 2 px
    table = {f"centre_{a}_mm": np.array([0.0, 0.0]) for a in "xy"}
    table["centre_z_mm"] = np.array([h - 4 * px, 0.0])
    for k in (1, 2, 3):
        table[f"semi_axis_{k}_mm"] = np.array([10 * px, [4, 5, 6][k - 1] * px])
    for i in (1, 2, 3):
        for j in (1, 2, 3):
            table[f"rotation_{i}{j}"] = np.array([float(i == j)] * 2)
    table.update(id=np.array([0.0, 1.0]), cut_top=np.array([1.0, 0.0]), cut_bottom=np.array([0.0, 0.0]))
    ball = S.visible_ball(table, meta)
    assert ball[1] == pytest.approx(4.0)
    assert ball[0] == pytest.approx(7.0, abs=1.0)


def test_voxel_route_runs_tracks_and_scores(sim, tmp_path):
    meta, tables, _ = S.flowing_truth(sim)
    D.run_voxel_route(sim, tmp_path / "vox", iterations=20)
    s = S.score_run(meta, tables, D.voxel_labels(tmp_path / "vox" / "labels.npz"))
    t = s["totals"]
    assert t["found"] > 0.5 * t["truth"]
    assert t["track_purity"] > 0.9 and t["tracks"] < t["rows"]  # ids carried from subscan to subscan
    text = D.format_table("voxel", s)
    assert text.count("\n") == len(s["subscans"]) + 2


def test_reversed_scan_runs_the_subscans_backwards_and_every_anew_bubble_has_an_event(sim, tmp_path):
    from bubsub.core.io.scanfile import read_scan

    a = read_scan(sim / "scan.h5")
    b = read_scan(D.reversed_scan(sim, tmp_path / "rev.h5"))
    assert b.projections_per_subscan == 8 and np.all(np.diff(b.time) > 0)
    for k in range(3):
        np.testing.assert_array_equal(b.data[8 * k:8 * k + 8], a.data[8 * (2 - k):8 * (3 - k)])
        np.testing.assert_array_equal(b.geometry.vectors[8 * k:8 * k + 8], a.geometry.vectors[8 * (2 - k):8 * (3 - k)])
    meta, tables, events = S.flowing_truth(sim)
    burden = S.chain_burden(meta, tables, events)
    for d in ("backward", "forward"):
        assert sum(burden[d]["reasons"].values()) == burden[d]["all"] > 0
        assert "other" not in burden[d]["reasons"]  # the events explain every bubble that comes or goes


def _write_lineage(folder, rows):
    with open(folder / "lineage.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, ["event", "subscan_before", "subscan", "time_s", "parent_ids", "child_ids", "reason"])
        w.writeheader()
        w.writerows({"time_s": "", "reason": "", **r} for r in rows)


def test_coalescences_are_scored_before_after_and_in_the_lineage_and_false_rows_counted(sim, tmp_path):
    meta, tables, events = S.flowing_truth(sim)
    (ev,) = [e for e in events if e["event"] == "coalesce"]
    k, child, parents = int(ev["subscan"]), int(ev["id"]), [int(p) for p in ev["parents"].split(";")]
    assert 1 <= k <= 2 and set(parents) <= set(tables[k - 1]["id"].astype(int))
    others = [int(i) for i in tables[k - 1]["id"] if int(i) not in parents and int(i) in set(tables[k]["id"])][:2]
    # the truth as the route, tracks = truth ids: the right row, a row between two bubbles that stay apart
    # (false), and a row naming the right bubbles between the wrong subscans (false too)
    rec = _fake_run(sim, tmp_path / "rec")
    right = {"event": "coalescence", "subscan_before": k - 1, "subscan": k, "parent_ids": f"{parents[0]};{parents[1]}",
             "child_ids": child}
    shifted = {**right, "subscan_before": k - 2 if k == 2 else 1, "subscan": k - 1 if k == 2 else 2}
    _write_lineage(rec, [right, {**right, "parent_ids": f"{others[0]};{others[1]}", "child_ids": others[0]},
                         shifted, {"event": "birth", "subscan_before": 0, "subscan": 1, "child_ids": others[1]}])
    c = S.score_run(meta, tables, D.bubsub_labels(rec, meta), events=events, lineage=S.read_lineage(rec))
    c = c["totals"]["coalescences"]
    assert (c["events"], c["two_before"], c["one_after"], c["in_lineage"], c["rows"], c["false_rows"]) == \
        (1, 1, 1, 1, 3, 2)
    assert c["in_lineage_a_subscan_off"] == 0 and c["false_rows_a_subscan_off"] == 1
    assert D.coalescence_cell(c) == "1 / 1 / 1, of 1; 2 of 3 (1 a true one a subscan off)"
    # the coalescence only a subscan off: not in the lineage, and its row false
    c = S.score_run(meta, tables, D.bubsub_labels(rec, meta), events=events, lineage=[shifted])
    c = c["totals"]["coalescences"]
    assert (c["in_lineage"], c["in_lineage_a_subscan_off"], c["false_rows"], c["false_rows_a_subscan_off"]) == \
        (0, 1, 1, 1)

    def keep_parents(j, meshes, ids):  # the child stays two bubbles: its parents' meshes, moved up by the flow
        if j != k:
            return meshes, ids
        before, before_ids = read_ply(sim / "truth" / f"subscan_{k - 1:04d}.ply", with_ids=True)
        up = np.array([0.0, 0.0, meta["flowing"]["flow_px_per_subscan"] * meta["column"]["pixel_size_mm"]])
        extra = [before[list(before_ids).index(p)] for p in parents]
        extra = [Mesh(np.asarray(m.vertices) + up, m.faces, m.attenuation) for m in extra]
        keep = [i for i, x in enumerate(ids) if x != child]
        return [meshes[i] for i in keep] + extra, [ids[i] for i in keep] + parents

    rec2 = _fake_run(sim, tmp_path / "rec2", keep_parents)
    c = S.score_run(meta, tables, D.bubsub_labels(rec2, meta), events=events)["totals"]["coalescences"]
    assert (c["two_before"], c["one_after"], c["in_lineage"], c["false_rows"]) == (1, 0, None, None)
    assert D.coalescence_cell(c) == "1 / 0 / -, of 1; -"
