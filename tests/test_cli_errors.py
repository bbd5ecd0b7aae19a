"""Every mistake a user can make on the command line is one line on stderr naming the problem and the fix.

No argparse usage block before it, no pydantic report, no uvicorn startup log, no Python warning with its
source line: exit status 2 and one line ``bubsub COMMAND: error: ...``.
"""

import socket

import pytest

from bubsub.clients.cli import main


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "sim"
    assert main(["simulate", "--bubbles", "3", "--det-count", "96", "--angles", "8", "--out", str(out)]) == 0
    return out


def _one_line_error(capsys, command, argv):
    assert main(argv) == 2, argv
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1, cap.err
    assert lines[0].startswith(f"bubsub {command}: error: "), lines[0]
    for noise in ("usage:", "Traceback", "https://", "validation error", "INFO:", ".py:"):
        assert noise not in lines[0], (noise, lines[0])
    assert cap.out == ""
    return lines[0]


@pytest.mark.parametrize("argv, words", [
    (["reconstruct", "missing.h5", "--out", "{tmp}/rec"], ["'missing.h5' does not exist", "existing file"]),
    (["reconstruct", "{sim}", "--out", "{tmp}/rec"], ["is a folder, not a file", "scan.h5"]),
    (["reconstruct", "{sim}/truth.json", "--out", "{tmp}/rec"], ["not a readable HDF5 file", "bubsub simulate"]),
    (["reconstruct", "{sim}/scan.h5"], ["required: --out", "--help"]),
    (["reconstruct", "{sim}/scan.h5", "--out", "{tmp}/rec", "--bogus"], ["unrecognized arguments: --bogus",
                                                                          "bubsub reconstruct --help"]),
    (["reconstruct", "{sim}/scan.h5", "--out", "{sim}/scan.h5"], ["is a file, not a folder"]),
    (["reconstruct", "{sim}/scan.h5", "--out", "{tmp}/rec", "--slabs", "2"], ["need a 3D scan", "leave --slabs out"]),
    (["reconstruct4d", "{sim}/scan.h5", "--out", "{tmp}/rec", "--iterations", "-3"], ["--iterations", "-3"]),
    (["reconstruct4d", "{sim}/scan.h5", "--out", "{tmp}/rec", "--warm-rtol", "nan"], ["--warm-rtol", "nan"]),
    (["reconstruct4d", "{sim}/scan.h5", "--out", "{tmp}/rec"], ["projections_per_subscan",
                                                                "--projections-per-subscan"]),
    (["simulate", "--det-count", "1", "--out", "{tmp}/sim"], ["--det-count", "at least 16"]),
    (["simulate", "--seed", "-1", "--out", "{tmp}/sim"], ["--seed", "-1"]),
    (["prepare", "{sim}/scan.h5", "--out", "{tmp}/p.h5", "--energy", "-1"], ["argument --energy: must be a positive number"]),
    (["serve", "--port", "99999"], ["--port", "0 to 65535", "99999"]),
    (["serve", "--port", "abc"], ["--port", "0 to 65535"]),
    (["serve", "--workers", "0"], ["--workers", ">= 1"]),
])
def test_user_mistakes_are_one_line(sim, tmp_path, capsys, argv, words):
    argv = [a.format(sim=sim, tmp=tmp_path) for a in argv]
    line = _one_line_error(capsys, argv[0], argv)
    assert all(w in line for w in words), line
    assert not (tmp_path / "rec").exists() and not (tmp_path / "sim").exists()


def test_an_unknown_command_names_the_commands(capsys):
    assert main(["recon", "x"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("bubsub: error: ") and "'reconstruct'" in err


def test_a_bad_server_setting_from_the_environment_names_its_variable(capsys, monkeypatch):
    monkeypatch.setenv("BUBSUB_PORT", "99999")
    monkeypatch.setenv("BUBSUB_MAX_BODY_BYTES", "1")
    line = _one_line_error(capsys, "serve", ["serve"])
    assert "BUBSUB_PORT" in line and "65535" in line and "BUBSUB_MAX_BODY_BYTES" in line


def test_a_port_in_use_is_one_line(capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        line = _one_line_error(capsys, "serve", ["serve", "--host", "127.0.0.1", "--port", str(port)])
    assert f"port {port}" in line and "in use" in line and "--port" in line


def test_an_unknown_host_is_one_line(capsys):
    line = _one_line_error(capsys, "serve", ["serve", "--host", "no-such-host.invalid", "--port", "0"])
    assert "--host 'no-such-host.invalid'" in line and "127.0.0.1" in line


def test_warnings_are_one_line_without_their_source(sim, tmp_path, capsys, monkeypatch):
    import bubsub.clients.pipeline.reconstruct4d as r4d
    from bubsub.core.io.subscans import subscan_layout

    def layout_only(scan, out, settings, projections_per_subscan=None, **_):
        subscan_layout(scan, projections_per_subscan)  # 8 projections in subscans of 3: the last 2 ignored
        raise ValueError("stopped after the layout")

    monkeypatch.setattr(r4d, "reconstruct_dynamic", layout_only)
    assert main(["reconstruct4d", str(sim / "scan.h5"), "--out", str(tmp_path / "rec"),
                 "--projections-per-subscan", "3", "--quiet"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == ["bubsub reconstruct4d: warning: projections_per_subscan = 3 does not divide the scan's 8 "
                     "projections: 2 complete subscans, the last 2 projections are ignored",
                     "bubsub reconstruct4d: error: stopped after the layout"]


def test_the_stand_alone_server_command_is_one_line_too(capsys):
    from bubsub.service.cli import main as service_main

    with pytest.raises(SystemExit) as refused:
        service_main(["--port", "99999"])
    assert refused.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--port" in err[0] and "usage:" not in err[0]
