"""The scale benchmark's parts: process-tree memory, bubble matching, the tomo_00080 projection."""

import math
import sys

import numpy as np
import pytest

from bubsub.bench.bubbles import per_bubble
from bubsub.bench.matching import match, overlaps
from bubsub.bench.scale import project, run_tree


def test_peak_memory_counts_the_grandchildren():
    # the child starts a grandchild that holds 300 MB for a second; the child itself stays small
    grandchild = "import time; b = bytearray(300 * 2**20); b[::4096] = b'x' * len(b[::4096]); time.sleep(1.5)"
    child = f"import subprocess, sys; subprocess.run([sys.executable, '-c', {grandchild!r}], check=True)"
    wall, cpu, rss = run_tree([sys.executable, "-c", child], poll=0.1)
    assert rss > 300 and wall > 1.5 and cpu >= 0
    with pytest.raises(Exception):
        run_tree([sys.executable, "-c", "raise SystemExit(3)"])


def _boxes(shape, boxes):
    out = np.zeros(shape, np.int32)
    for k, sl in enumerate(boxes, start=1):
        out[sl] = k
    return out


def test_match_found_missed_merged_spurious():
    shape = (4, 40, 40)
    truth = _boxes(shape, [np.s_[:, 0:10, 0:10], np.s_[:, 0:10, 12:20], np.s_[:, 0:10, 22:30], np.s_[:, 20:30, 0:10],
                           np.s_[:, 30:40, 30:40]])
    rec = _boxes(shape, [np.s_[:, 0:10, 1:10],      # truth 1: IoU 0.9, found
                         np.s_[:, 0:10, 12:30],     # truths 2 and 3 merged
                         np.s_[:, 20:30, 0:3],      # truth 4: IoU 0.3, missed
                         np.s_[:, 12:18, 30:38]])   # nobody's: spurious; truth 5 has nothing
    res = match(truth, rec, cut=np.array([1, 1, 0, 0, 1], bool))
    assert (res["found"], res["merged"], res["missed"], res["spurious"]) == (1, 2, 2, 1)
    assert (res["cut_truth"], res["cut_found"], res["cut_merged"], res["cut_missed"]) == (3, 1, 1, 1)
    assert res["per_truth"][0][1:3] == (1, pytest.approx(0.9))
    inter = 360 + 2 * 320 + 120
    assert res["ddi"] == pytest.approx(1 - 2 * inter / (truth.astype(bool).sum() + rec.astype(bool).sum()))


def test_match_agrees_with_per_bubble_on_random_labels():
    rng = np.random.default_rng(0)
    truth = rng.integers(0, 7, size=(6, 12, 12)).astype(np.int32)
    rec = np.where(rng.uniform(size=truth.shape) < 0.8, truth, rng.integers(0, 9, size=truth.shape)).astype(np.int32)
    rows, owner = per_bubble(truth, rec)
    res = match(truth, rec)
    for (i, _, j, ddi, merged), (label, best, iou, status) in zip(rows, res["per_truth"]):
        assert (i, j) == (label, best)
        assert iou == pytest.approx((1 - ddi) / (1 + ddi))  # IoU from the Dice dissimilarity
        assert (status == "merged") == bool(merged)
    table, n_t, n_r = overlaps(truth, rec)
    assert table.sum() + np.sum((truth == 0) & (rec == 0)) == truth.size and n_t.sum() == n_r.sum() == truth.size


def test_projection_from_slabs_and_from_a_whole_run():
    shape = (40, 256, 768)
    slabs = [{"seconds_total": 100.0, "core_rows": [0, 64], "read_rows": [0, 96], "bubbles": 150},
             {"seconds_total": 100.0, "core_rows": [64, 128], "read_rows": [32, 160], "bubbles": 150}]
    report = {"seconds_total": 400.0, "bubbles": 600, "slabs": slabs}
    tomo = (300, 1800, 2016)
    full, binned = project(report, shape, 600, tomo=tomo, tomo_bubbles=30000)
    # median slab: 112 rows read (core 64, halo 24), 100 s, 150 bubbles
    per_pb = np.median([100 / (40 * 96 * 768 * 150), 100 / (40 * 128 * 768 * 150)])
    read = 64 + 48
    slab = per_pb * (300 * read * 2016) * (30000 * read / 1800)
    assert full["slabs"] == math.ceil(1800 / 64) == 29
    assert full["seconds"]["pixels x bubbles"][1] == pytest.approx(29 * slab)
    assert full["seconds"]["pixels x bubbles"][16] == pytest.approx(2 * slab)
    assert binned["slabs"] == math.ceil(900 / 32) and binned["shape"] == (300, 900, 1008)
    whole = project({"seconds_total": 400.0, "bubbles": 600}, shape, 600, tomo=tomo)[0]
    assert whole["slabs"] == math.ceil(1800 / 256) and whole["bubbles"] == pytest.approx(600 * 1800 * 2016**2
                                                                                          / (256 * 768**2))
    assert whole["seconds"]["pixels"][1] == pytest.approx(8 * 400 / (40 * 256 * 768) * 300 * 256 * 2016)
    # the subscan's slabs of a whole run's rows read a halo as well
    haloed = project({"seconds_total": 400.0, "bubbles": 600}, shape, 600, tomo=tomo, halo_rows=40)[0]
    assert haloed["seconds"]["pixels"][1] == pytest.approx(8 * 400 / (40 * 256 * 768) * 300 * (256 + 80) * 2016)


def test_watershed_splits_two_touching_balls():
    from bubsub.bench.fov import watershed_bubbles

    z, y, x = np.indices((30, 30, 50))
    mask = ((x - 15) ** 2 + (y - 15) ** 2 + (z - 15) ** 2 <= 100) | ((x - 32) ** 2 + (y - 15) ** 2 + (z - 15) ** 2 <= 100)
    labels = watershed_bubbles(mask)
    assert labels.max() == 2 and np.array_equal(labels > 0, mask)
    assert labels[15, 15, 15] != labels[15, 15, 32]


def test_fov_column_case_scores_the_truth_as_found(tmp_path, capsys):
    from bubsub.bench.fov import main as fov_main
    from bubsub.clients.cli.main import main

    sim, rec = tmp_path / "sim", tmp_path / "rec"
    assert main(["simulate", "--phantom", "column", "--bubbles", "25", "--det-count", "96", "--angles", "12",
                 "--out", str(sim)]) == 0
    rec.mkdir()
    (rec / "bubbles.ply").write_bytes((sim / "truth.ply").read_bytes())
    capsys.readouterr()
    assert fov_main(["--column", "25", "--column-data", str(sim), "--rec", str(rec), "--sirt-iterations", "10",
                     "--out", str(tmp_path / "out")]) == 0
    lines = [line.split("|")[1:-1] for line in capsys.readouterr().out.splitlines() if line.startswith("| ")]
    header, bubsub, voxel = lines
    row = dict(zip([h.strip() for h in header], [c.strip() for c in bubsub]))
    assert row["found"] == row["truth"] and row["merged"] == row["spurious"] == "0" and float(row["DDI in FOV"]) < 0.01
    assert "SIRT 10" in voxel[0]
