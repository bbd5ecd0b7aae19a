"""reconstruct4d on a Dask cluster (loopback only, 2 single-threaded workers): one chain gives the
in-process meshes, two chunks give linked ids and the in-process accuracy, a worker killed mid-run
changes nothing."""

import csv
import json
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from bubsub.clients.cli.main import main
from bubsub.clients.cluster.chunks import chunk_bounds, link_ids
from bubsub.clients.cluster.engine import local, open_client
from bubsub.clients.pipeline.dynamic4d.chain import BubbleState, DynamicSettings
from bubsub.clients.pipeline.reconstruct4d import reconstruct_dynamic
from bubsub.clients.pipeline.evaluation.evaluate4d import evaluate_dynamic
from bubsub.core import circle_surface
from bubsub.core.io.scanfile import read_scan

RUN = ["--holdout", "odd", "--iterations", "20", "--quiet"]
SETTINGS = DynamicSettings(iterations=20, holdout="odd", progress=False)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim4d")
    assert main(["simulate", "--phantom", "expanding2d", "--bubbles", "6", "--det-count", "240", "--subscans", "3",
                 "--projections-per-subscan", "16", "--seed", "5", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def in_process(sim, tmp_path_factory):
    """The in-process run, its projector and BLAS on 1 thread as on the workers: sums are reduced in an order
    that depends on the thread count, and BFGS turns those 1e-16 differences into 1e-6 mm ones (and a voxel
    preview's into other seeds)."""
    out = tmp_path_factory.mktemp("local4d")
    mp = pytest.MonkeyPatch()
    mp.setenv("BUBSUB_THREADS", "1")
    try:
        with threadpool_limits(limits=1):
            assert main(["reconstruct4d", str(sim / "scan.h5"), "--out", str(out), *RUN]) == 0
    finally:
        mp.undo()
    return out


@pytest.fixture(scope="module")
def client():
    with open_client(local(2)) as c:
        yield c


def controls(out):
    """``{subscan folder: {track id: control vertices}}`` of a 2D run."""
    return {p.name: {b["id"]: np.array(b["vertices"]) for b in json.loads((p / "control.json").read_text())["bubbles"]}
            for p in sorted(Path(out).glob("subscan_*"))}


def assert_same_meshes(a, b):
    """Same subscans, same ids, same control vertices (to 1e-9 mm)."""
    ca, cb = controls(a), controls(b)
    assert list(ca) == list(cb) and all(list(ca[k]) == list(cb[k]) for k in ca)
    for k in ca:
        for i in ca[k]:
            np.testing.assert_allclose(ca[k][i], cb[k][i], rtol=0, atol=1e-9, err_msg=f"{k} bubble {i}")


def test_chunk_bounds_overlap_by_one_subscan():
    assert chunk_bounds([7, 6, 5, 4, 3, 2, 1, 0], 2) == [[7, 6, 5, 4, 3], [3, 2, 1, 0]]
    assert chunk_bounds([7, 6, 5, 4, 3, 2, 1, 0], 3) == [[7, 6, 5], [5, 4, 3, 2], [2, 1, 0]]
    assert chunk_bounds([2, 1], 5) == [[2, 1]]  # no chunk shorter than two subscans
    with pytest.raises(ValueError, match="chunks must be a positive integer"):
        chunk_bounds([1, 0], 0)


def test_link_ids_is_one_to_one_by_overlap():
    later = BubbleState.from_surfaces([10, 11, 12], [circle_surface((x, 0.0), 0.5, -0.1) for x in (0.0, 2.0, 4.0)])
    # the earlier chunk's cold start: same bubbles slightly moved, other order, one extra
    earlier = BubbleState.from_surfaces([0, 1, 2, 3], [circle_surface((x, 0.05), 0.48, -0.1)
                                                       for x in (4.02, 0.0, 2.03, 8.0)])
    matches, overlaps = link_ids(earlier, later)
    assert matches == {0: 12, 1: 10, 2: 11}  # bubble 3 overlaps nothing: unmatched
    assert all(0.8 < v <= 1 for v in overlaps.values())


def test_one_chain_on_two_workers_gives_the_in_process_meshes(sim, in_process, tmp_path):
    out = tmp_path / "w2"
    assert main(["reconstruct4d", str(sim / "scan.h5"), "--out", str(out), *RUN, "--workers", "2"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["engine"] == "dask" and report["workers"] == 2 and report["chunks"] == 1
    assert_same_meshes(out, in_process)


def test_two_chunks_link_ids_and_keep_the_accuracy(sim, in_process, client, tmp_path):
    report = reconstruct_dynamic(read_scan(sim / "scan.h5"), tmp_path, SETTINGS, client=client, chunks=2)
    assert report["engine"] == "dask" and report["chunks"] == 2 and report["subscans_complete"] == 3
    (link,) = report["chunk_links"]
    assert link["subscan"] == 1 and link["matched"] == 6 and link["unmatched_later"] == []
    # the ids of the earlier chunk are the later chunk's: every track follows one true bubble through the boundary
    ours, ref = evaluate_dynamic(tmp_path, sim), evaluate_dynamic(in_process, sim)
    assert ours["right_track_fraction"] == 1.0
    assert ours["mean_ddi"] <= 1.1 * ref["mean_ddi"]
    # the earlier chunk's cold start at 8 views keeps a sliver between two touching bubbles that the later chunk
    # lacks there and its own next subscan drops: no written subscan holds it, so it is no track and no event
    written = {int(row["bubble_id"]) for row in csv.DictReader((tmp_path / "tracks.csv").open())}
    assert written == set(range(6)) and report["totals"]["tracks"] == 6
    assert not {int(k) for k in link["unmatched_earlier"]} & written
    assert list(csv.DictReader((tmp_path / "lineage.csv").open())) == []


def test_a_worker_killed_mid_run_changes_nothing(sim, in_process, client, tmp_path):
    pids = client.run(os.getpid)
    done = {}
    run = threading.Thread(target=lambda: done.update(
        report=reconstruct_dynamic(read_scan(sim / "scan.h5"), tmp_path, SETTINGS, client=client)))
    run.start()
    killed = None
    end = time.monotonic() + 240
    while run.is_alive() and killed is None and time.monotonic() < end:
        # kill the worker while it fits the second subscan (warm-started from the first one's result)
        busy = [w for w, keys in client.processing().items() if any(str(k).startswith("subscan-0001") for k in keys)]
        if busy and busy[0] in pids:
            killed = pids[busy[0]]
            os.kill(killed, signal.SIGKILL)
        time.sleep(0.02)
    run.join(300)
    assert killed is not None and not run.is_alive()
    assert done["report"]["subscans_complete"] == 3 and not done["report"]["interrupted"]
    assert_same_meshes(tmp_path, in_process)
    # the nanny brought the worker back
    client.wait_for_workers(2, timeout=60)
    assert killed not in client.run(os.getpid).values()
