"""Progress: one summary line per phase when not on a terminal, with the reason each fit stopped."""

import io

import numpy as np
import pytest

from bubsub.clients.cli import main
from bubsub.clients.optimise.fit import fit
from bubsub.clients.progress import phase
from bubsub.core import MeshProjector, ScanGeometry, circle_surface


@pytest.fixture(scope="module")
def disc_scene():
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 12, endpoint=False), pixel_size=0.02, cols=160)
    P = MeshProjector(g)
    truth = [circle_surface([0.2, -0.1], 0.6, -0.1, control=12)]
    return P, P.forward(truth)


def test_a_redirected_phase_prints_one_line_with_its_stop_reason(monkeypatch):
    monkeypatch.delenv("BUBSUB_PROGRESS", raising=False)
    out = io.StringIO()  # not a terminal
    bar = phase("BubSub fit", 80, stream=out)
    for _ in range(57):
        bar.update(1, f="0.5")
    bar.close("converged")
    bar.close("twice is harmless")
    assert out.getvalue().count("\n") == 1
    assert out.getvalue().startswith("BubSub fit: 57 iterations, ") and "converged, f = 0.5" in out.getvalue()
    silent = io.StringIO()
    with phase("quiet", 3, enabled=False, stream=silent) as q:
        q.update(3)
    assert silent.getvalue() == ""


def test_a_terminal_bar_ends_at_its_own_count_with_the_reason(monkeypatch):
    monkeypatch.setenv("BUBSUB_PROGRESS", "bar")
    out = io.StringIO()
    bar = phase("BubSub fit", 80, stream=out)
    bar.update(57)
    bar.close("converged")
    last = out.getvalue().replace("\r", "\n").strip().splitlines()[-1]
    assert "57/57" in last and "100%" in last and "converged" in last


def test_fit_reports_why_it_stopped(disc_scene):
    P, data = disc_scene
    start = [circle_surface([0.25, -0.05], 0.5, -0.1, control=12)]
    assert fit(P, start, data, iterations=2, progress=False).stop_reason == "iteration limit"
    done = fit(P, start, data, iterations=500, progress=False)
    assert done.stop_reason == "converged" and done.iterations < 500
    assert fit(P, start, data, iterations=500, method="lbfgs", progress=False).stop_reason == "converged"
    stopped = fit(P, start, data, iterations=50, progress=False, callback=lambda k, f, s: k == 3)
    assert stopped.stop_reason == "stopped early" and stopped.iterations == 3
    # a caller's own reason, in its words, is the fit's
    said = fit(P, start, data, iterations=50, progress=False, callback=lambda k, f, s: "stopped: enough" if k == 2 else None)
    assert said.stop_reason == "stopped: enough" and said.iterations == 2

    def interrupt(k, f, s):
        raise KeyboardInterrupt

    assert fit(P, start, data, iterations=50, progress=False, callback=interrupt).stop_reason == "interrupted"


def test_redirected_reconstruct_prints_one_line_per_phase(tmp_path, capsys, monkeypatch):
    import json

    monkeypatch.delenv("BUBSUB_PROGRESS", raising=False)
    sim = tmp_path / "sim"
    assert main(["simulate", "--bubbles", "4", "--det-count", "200", "--angles", "8", "--out", str(sim)]) == 0
    capsys.readouterr()
    rc = main(["reconstruct", str(sim / "scan.h5"), "--out", str(tmp_path / "rec"), "--iterations", "5"])
    assert rc == 0
    err = capsys.readouterr().err.strip().splitlines()
    names = [line.split(":")[0] for line in err]
    # 2D picks its initial centres from two candidate sets (LoG blobs, distance-transform maxima), each radius-fitted;
    # a topology round that changes the bubbles refits them
    assert names[0].startswith("voxel preview (2D") and names[1:4] == [
        "radius estimation (LoG centres)", "radius estimation (distance-transform centres)", "BubSub fit"]
    # then the topology rounds (each timed whole, its refit a phase of its own) and the coarse-to-fine trial
    # (clients/pipeline/static/refine.py), when it runs
    assert names[4] in ("topology round 1", "topology round 1 refit")  # a round's refit ends before the round
    assert "topology round 1" in names[4:]
    assert all(n.startswith("topology round") or n == "refined fit" for n in names[4:-1]) and names[-1] == "pictures"
    assert "\r" not in "\n".join(err) and "callback" not in "\n".join(err)
    assert "iteration limit" in err[3]
    assert err[-1].startswith("pictures: 2 pictures")  # overlay and size histogram (2D)
    report = json.loads((tmp_path / "rec" / "report.json").read_text())
    assert report["stop_reason"] == "iteration limit" and report["iterations"] == 5


def _seconds(line):
    """The seconds a phase's summary line gives (``name: 4 steps, 0.3 s, ...``)."""
    return float(next(w for w in line.split(", ") if w.endswith(" s")).split()[0])


def test_a_topology_round_is_one_phase_timed_from_its_start(disc_scene, capsys, monkeypatch):
    import time

    from bubsub.clients.pipeline.static.topology import adapt_topology

    monkeypatch.delenv("BUBSUB_PROGRESS", raising=False)
    P, data = disc_scene

    def slow_preview(projections):  # the residual's voxel preview, the round's first cost: nothing in it
        time.sleep(0.3)
        return np.zeros((32, 32)), (-1.6, 1.6, -1.6, 1.6)

    truth = [circle_surface([0.2, -0.1], 0.6, -0.1, control=12)]
    adapt_topology(P, truth, data, preview=slow_preview, rounds=2, min_radius=0.05, max_radius=0.5,
                   new_bubble=lambda c, r: circle_surface(c, r, -0.1, control=12), progress=True,
                   steps=("remove", "add"))
    err = capsys.readouterr().err.strip().splitlines()
    # a round that changes nothing ends the rounds: one line, with the time its changes took
    assert len(err) == 1 and err[0].startswith("topology round 1: 2 steps, ") and err[0].endswith("no change")
    assert _seconds(err[0]) >= 0.3


def test_redirected_subscans_print_one_plain_line_each(capsys, monkeypatch):
    from types import SimpleNamespace

    from bubsub.clients.pipeline.dynamic4d.chain import run_chain

    monkeypatch.delenv("BUBSUB_PROGRESS", raising=False)

    def step(scan, state, settings, k, t):
        return SimpleNamespace(report={}, state=[1, 2, 3], ended=(7,))

    results, interrupted = run_chain(lambda k: None, [2, 1, 0], SimpleNamespace(progress=True), step=step)
    assert len(results) == 3 and not interrupted
    err = capsys.readouterr().err
    assert "\r" not in err  # no bar in a log file
    lines = err.strip().splitlines()
    assert len(lines) == 4 and lines[0].startswith("subscans: 1 of 3 done, ")
    assert "subscan = 2, bubbles = 3, ended = 1" in lines[0] and lines[-1].startswith("subscans: 3 subscans, ")
