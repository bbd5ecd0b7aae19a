import csv
import json

import pytest

from bubsub.clients.cli.main import main
from bubsub.clients.experiments.runner import EXPERIMENTS, format_table, summarise


def test_quick_experiment_writes_csv_png_and_summary(tmp_path):
    rc = main(["experiment", "fig5", "--quick", "--values", "1.0", "--out", str(tmp_path), "--quiet"])
    assert rc == 0
    with open(tmp_path / "fig5.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["method"] for r in rows] == ["bubsub"]
    assert 0 <= float(rows[0]["ddi"]) < 0.05  # a good initial radius gives a good fit
    summary = json.loads((tmp_path / "fig5.json").read_text())
    assert summary["methods"]["bubsub"]["1.0"]["n"] == 1
    assert (tmp_path / "fig5.png").read_bytes()[:4] == b"\x89PNG"


def test_baselines_and_bubsub_are_scored_on_one_grid(tmp_path):
    from bubsub.clients.experiments.runner import QUICK_2D, run_case, simulate_case

    ph, scan, shape, extent = simulate_case(2, 0, 20, 1e4, QUICK_2D, quick=True)
    scores = {m: run_case(m, scan, ph, shape, extent, iterations=40)[0] for m in ("fbp", "sirt", "bubsub")}
    assert all(0 <= v <= 1 for v in scores.values())
    assert scores["bubsub"] < 0.5 * min(scores["fbp"], scores["sirt"])


def test_summary_table():
    rows = [{"angles": a, "method": m, "ddi": d} for a, m, d in [(10, "fbp", 0.4), (10, "fbp", 0.2), (10, "bubsub", 0.01)]]
    s = summarise(rows, "angles")
    assert s["methods"]["fbp"]["10"]["mean"] == pytest.approx(0.3)
    assert s["methods"]["fbp"]["10"]["std"] == pytest.approx(0.1)
    assert "0.3000" in format_table(s, "angles")
    assert set(EXPERIMENTS) == {"fig1a", "fig1b", "fig5", "fig3a", "dense2d", "dense3d"}


def test_unknown_experiment_is_refused(tmp_path, capsys):
    assert main(["experiment", "fig9", "--out", str(tmp_path)]) == 2
    assert "invalid choice" in capsys.readouterr().err


def _fake_runs(path, quick):
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["experiment", "radius", "method", "seed", "ddi", "seconds", "quick"])
        w.writeheader()
        w.writerow({"experiment": "fig5", "radius": 1.0, "method": "bubsub", "seed": 0, "ddi": 0.0123, "seconds": 1.0, "quick": quick})


def test_resume_keeps_finished_runs_and_runs_only_missing_ones(tmp_path):
    _fake_runs(tmp_path / "fig5.csv", True)
    # everything asked for is already there: nothing is recomputed, the summary covers it
    rc = main(["experiment", "fig5", "--quick", "--values", "1.0", "--out", str(tmp_path), "--quiet", "--resume"])
    assert rc == 0
    summary = json.loads((tmp_path / "fig5.json").read_text())
    assert summary["methods"]["bubsub"]["1.0"] == {"mean": 0.0123, "std": 0.0, "n": 1}
    with open(tmp_path / "fig5.csv") as f:
        assert len(list(csv.DictReader(f))) == 1


def test_resume_refuses_runs_of_the_other_mode_and_unknown_methods(tmp_path, capsys):
    _fake_runs(tmp_path / "fig5.csv", True)
    assert main(["experiment", "fig5", "--values", "1.0", "--out", str(tmp_path), "--quiet", "--resume"]) != 0
    assert "quick-mode runs" in capsys.readouterr().err
    assert main(["experiment", "fig5", "--quick", "--methods", "sirt", "--out", str(tmp_path), "--quiet"]) != 0
    assert "no method(s) ['sirt']" in capsys.readouterr().err


def test_ctrl_c_inside_a_fit_stops_the_experiment_and_keeps_the_finished_runs(tmp_path, monkeypatch):
    # fit() turns Ctrl-C into an "interrupted" result; an experiment must not score it as a
    # finished run and go on with the next one
    from bubsub.clients.experiments import runner
    from bubsub.core import MeshProjector

    armed = {"on": False}
    objective, run_setting = MeshProjector.objective, runner.run_setting

    def interruptible(self, meshes, data):
        if armed["on"]:
            raise KeyboardInterrupt
        return objective(self, meshes, data)

    def first_run_then_ctrl_c(*args):
        row = run_setting(*args)
        armed["on"] = True  # the next run's first fit is interrupted
        return row

    monkeypatch.setattr(MeshProjector, "objective", interruptible)
    monkeypatch.setattr(runner, "run_setting", first_run_then_ctrl_c)
    rc = main(["experiment", "fig5", "--quick", "--values", "1.0", "2.0", "--out", str(tmp_path), "--quiet"])
    assert rc == 130
    with open(tmp_path / "fig5.csv") as f:
        rows = list(csv.DictReader(f))
    assert [float(r["radius"]) for r in rows] == [1.0]
    assert json.loads((tmp_path / "fig5.json").read_text())["interrupted"] is True


def test_experiment_folders_follow_the_output_folder_policy(tmp_path, capsys):
    from bubsub.clients.pipeline.results.outputs import MANIFEST

    _fake_runs(tmp_path / "fig5.csv", True)
    args = ["experiment", "fig5", "--quick", "--values", "1.0", "--out", str(tmp_path), "--quiet"]
    # this experiment's earlier results: refused before any computation unless --resume or --overwrite
    assert main(args) == 2
    assert "already holds results of experiment fig5" in capsys.readouterr().err
    assert main(args + ["--resume"]) == 0
    manifest = json.loads((tmp_path / MANIFEST).read_text())
    assert manifest["command"] == "experiment"
    assert manifest["experiments"] == {"fig5": ["fig5.csv", "fig5.csv-metadata.json", "fig5.json", "fig5.png"]}
    # another experiment shares the folder; both stay listed and on disk
    with open(tmp_path / "fig1a.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["experiment", "angles", "method", "seed", "ddi", "seconds", "quick"])
        w.writeheader()
        w.writerow({"experiment": "fig1a", "angles": 10, "method": "fbp", "seed": 0, "ddi": 0.3, "seconds": 1.0,
                    "quick": True})
    assert main(["experiment", "fig1a", "--quick", "--values", "10", "--methods", "fbp", "--out", str(tmp_path),
                 "--quiet", "--resume"]) == 0
    manifest = json.loads((tmp_path / MANIFEST).read_text())
    assert sorted(manifest["experiments"]) == ["fig1a", "fig5"] and len(manifest["files"]) == 8  # 4 files each
    assert all((tmp_path / f).is_file() for f in manifest["files"])
    # a folder holding another command's results is refused unless --overwrite
    rec = tmp_path / "rec"
    rec.mkdir()
    (rec / "report.json").write_text("{}")
    assert main(["experiment", "fig5", "--quick", "--out", str(rec), "--quiet"]) == 2
    assert "--overwrite" in capsys.readouterr().err and (rec / "report.json").is_file()


def test_ctrl_c_inside_a_fig6_fit_stops_the_experiment(tmp_path, monkeypatch, capsys):
    from bubsub.clients.pipeline import reconstruct4d

    def interrupted_chain(scan, out, settings, **kw):
        # what reconstruct_dynamic returns when Ctrl-C stops a fit after the last subscan was finished
        (out / "subscan_0001").mkdir(parents=True)
        (out / "subscan_0001" / "report.json").write_text("{}")
        return {"interrupted": True, "subscans": [{"subscan": 1}]}

    monkeypatch.setattr(reconstruct4d, "reconstruct_dynamic", interrupted_chain)
    assert main(["experiment", "fig6", "--quick", "--out", str(tmp_path), "--quiet"]) == 130
    assert "rerun with --resume" in capsys.readouterr().out
    assert not (tmp_path / "fig6.csv").exists()  # nothing scored
    manifest = json.loads((tmp_path / "bubsub-outputs.json").read_text())
    assert "bubsub/subscan_0001/report.json" in manifest["files"] and "sim/scan.h5" in manifest["files"]
    # the kept subscans are this experiment's results: a plain rerun is refused
    assert main(["experiment", "fig6", "--quick", "--out", str(tmp_path), "--quiet"]) == 2
