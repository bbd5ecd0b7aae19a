"""The command line refuses bad input before computing: arguments, output folders, scan signal, --server."""

import json
import socket
import time

import h5py
import pytest

from bubsub.clients.cli import main
from bubsub.clients.pipeline.inputs.checks import check_bubble_signal, check_settings
from bubsub.clients.pipeline.results.outputs import MANIFEST, OutputFolderError, check_output_folder, finish_outputs
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings
from bubsub.core.io.scanfile import read_scan


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "sim"
    assert main(["simulate", "--bubbles", "4", "--det-count", "200", "--angles", "8", "--out", str(out)]) == 0
    return out


def _copy_scan(sim, path, *, contrast_sign=1, background=True):
    import shutil

    shutil.copy(sim / "scan.h5", path)
    with h5py.File(path, "a") as f:
        if not background:
            del f["exchange/background"]
        f.attrs["bubble_contrast"] = contrast_sign * f.attrs["bubble_contrast"]
    return path


def test_version(capsys):
    from bubsub.clients import version

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"bubsub {version()}"
    assert version() != "unknown"


@pytest.mark.parametrize("argv, words", [
    (["--iterations", "-5"], "--iterations: must be 0 or a positive integer"),
    (["--levels", "x"], "--levels: must be an integer"),
    (["--radius", "0"], "--radius: must be positive"),
    (["--levels", "7"], "--levels must be at most 4"),
    (["--facet-pixels", "-0.1"], "--facet-pixels must be a number of pixels >= 0"),
    (["--facet-pixels", "nan"], "--facet-pixels must be a number of pixels >= 0"),
    (["--control-points", "2"], "--control-points must be an integer >= 3"),
    (["--token", "abc"], "--token is only used with --server"),
])
def test_bad_arguments_are_refused_before_anything_is_written(sim, tmp_path, capsys, argv, words):
    out = tmp_path / "rec"
    t0 = time.perf_counter()
    assert main(["reconstruct", str(sim / "scan.h5"), "--out", str(out), "--quiet", *argv]) == 2
    assert time.perf_counter() - t0 < 3  # refused before the voxel preview (which takes longer)
    assert words in capsys.readouterr().err
    assert not out.exists()


def test_out_naming_a_file_or_lying_under_one(sim, tmp_path, capsys):
    f = tmp_path / "afile"
    f.write_text("x")
    for out, words in ((f, "is a file, not a folder"), (f / "sub", "is a file")):
        assert main(["reconstruct", str(sim / "scan.h5"), "--out", str(out), "--quiet"]) == 2
        assert words in capsys.readouterr().err
    assert f.read_text() == "x"


def test_settings_checks_name_the_option():
    with pytest.raises(ValueError, match=r"--control-points must be one of \[12, 42, 162\]"):
        check_settings(ReconstructionSettings(control_points=9), 3)
    check_settings(ReconstructionSettings(control_points=9), 2)
    with pytest.raises(ValueError, match="--iterations"):
        check_settings(ReconstructionSettings(iterations=-1), 2)


def test_a_folder_with_results_is_refused_without_overwrite(sim, tmp_path, capsys):
    assert main(["simulate", "--bubbles", "4", "--det-count", "200", "--angles", "8", "--out", str(sim)]) == 2
    err = capsys.readouterr().err
    assert "--overwrite" in err and "simulate" in err
    # an old folder without manifest is recognised by its file names
    legacy = tmp_path / "legacy"
    legacy.mkdir()
    (legacy / "report.json").write_text("{}")
    with pytest.raises(OutputFolderError, match="--overwrite"):
        check_output_folder(legacy)
    assert check_output_folder(legacy, overwrite=True) == legacy
    # an empty folder, or one with unrelated files, is fine
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "readme.txt").write_text("mine")
    check_output_folder(tmp_path / "notes")


def test_overwrite_removes_every_file_of_the_earlier_run(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    for name in ("bubbles.ply", "control.ply", "report.json", "extra3d.png"):
        (out / name).write_text("old")
    (out / "mine.txt").write_text("not bubsub's")
    finish_outputs(out, [out / "bubbles.ply", out / "control.ply", out / "report.json", out / "extra3d.png"],
                   command="reconstruct")
    (out / "bubbles.json").write_text("new")
    (out / "report.json").write_text("new")
    removed = finish_outputs(out, [out / "bubbles.json", out / "report.json"], command="reconstruct")
    assert sorted(p.name for p in removed) == ["bubbles.ply", "control.ply", "extra3d.png"]
    assert sorted(p.name for p in out.iterdir()) == sorted([MANIFEST, "bubbles.json", "mine.txt", "report.json"])
    doc = json.loads((out / MANIFEST).read_text())
    assert doc["command"] == "reconstruct" and doc["files"] == ["bubbles.json", "report.json"]


def test_simulate_overwrite_replaces_a_reconstruction_folder(sim, tmp_path):
    out = tmp_path / "mixed"
    out.mkdir()
    (out / "bubbles.ply").write_text("old 3D result")
    assert main(["simulate", "--bubbles", "3", "--det-count", "200", "--angles", "8", "--out", str(out),
                 "--overwrite"]) == 0
    assert not (out / "bubbles.ply").exists()
    assert (out / "scan.h5").is_file()


@pytest.mark.parametrize("sign, background, words", [
    (1, False, "no /exchange/background and its projections are mostly positive"),
    (-1, False, "pass --background-subtracted"),
    (-1, True, "disagrees with the data"),
])
def test_background_and_contrast_sign_mistakes_are_refused_in_seconds(sim, tmp_path, capsys, sign, background,
                                                                      words):
    scan = _copy_scan(sim, tmp_path / "bad.h5", contrast_sign=sign, background=background)
    t0 = time.perf_counter()
    assert main(["reconstruct", str(scan), "--out", str(tmp_path / "rec"), "--quiet"]) == 2
    assert time.perf_counter() - t0 < 3
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1
    if not background:
        assert "bubsub prepare --background auto" in err
    assert not (tmp_path / "rec").exists()


def test_correct_scans_pass_the_signal_check(sim, tmp_path):
    check_bubble_signal(read_scan(sim / "scan.h5"))
    # a scan holding only the bubbles' (negative) projection needs no background
    scan = read_scan(sim / "scan.h5")
    scan.data, scan.background = scan.bubble_data, None
    check_bubble_signal(scan)
    # a positive contrast without background is accepted when the user says the data are the bubbles'
    scan.data, scan.bubble_contrast = -scan.data, -scan.bubble_contrast
    check_bubble_signal(scan, background_subtracted=True)
    with pytest.raises(ValueError, match="positive bubble_contrast"):
        check_bubble_signal(scan)


def test_an_unreachable_server_fails_fast_with_one_line(sim, tmp_path, capsys):
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        url = f"http://127.0.0.1:{s.getsockname()[1]}"
    t0 = time.perf_counter()
    assert main(["reconstruct", str(sim / "scan.h5"), "--out", str(tmp_path / "rec"), "--server", url]) == 2
    assert time.perf_counter() - t0 < 20
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and url in err and "Traceback" not in err


def test_unexpected_errors_are_one_line_unless_debug(monkeypatch, capsys):
    import bubsub.clients.cli.evaluate as ev

    def boom(*_):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(ev, "evaluate_dir", boom)
    assert main(["evaluate", "a", "b"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == "bubsub evaluate: error: RuntimeError: disk on fire (bubsub --debug ... shows the traceback)"
    with pytest.raises(RuntimeError, match="disk on fire"):
        main(["--debug", "evaluate", "a", "b"])


def test_help_texts_are_complete(capsys):
    for argv, words in ((["bench", "--help"], ["projector", "remote", "--help"]),
                        (["demo", "--help"], ["--out", "default demo-output", "--overwrite"]),
                        (["experiment", "--help"], ["fig1a", "fig3a", "--resume", "methods"])):
        assert main(argv) == 0
        out = capsys.readouterr().out
        assert all(w in out for w in words), (argv, out)
