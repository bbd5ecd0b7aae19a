"""Deployment: what docker/Dockerfile does, done here without a Docker engine.

The image builds a wheel of the project (``pip wheel --no-deps``), installs only
that wheel in a clean Python, runs its ``CMD`` and health-checks it with its
``HEALTHCHECK``. The test does the same with a fresh virtual environment (no
system site-packages) into which only the wheel is installed; the wheel's
dependencies are taken from the test's own environment through a ``.pth``
file instead of being downloaded again. The compose file must stay valid YAML
with the documented services and settings.
"""

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import sysconfig
import time
import urllib.request
import venv
import zipfile
from pathlib import Path

import pytest
import yaml

from bubsub.service.config import Settings

ROOT = Path(__file__).resolve().parents[1]
DOCKER = ROOT / "docker"


def dockerfile_stages():
    """``[(stage header, [instructions])]`` of docker/Dockerfile (continuations joined)."""
    text = (DOCKER / "Dockerfile").read_text()
    text = re.sub(r"\\\n", " ", text)
    stages = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        if line.upper().startswith("FROM "):
            stages.append((line, []))
        elif stages:
            stages[-1][1].append(line)
    return stages


def exec_form(instruction):
    """The JSON exec form of a CMD/HEALTHCHECK instruction as a list."""
    return json.loads(instruction[instruction.index("["):])


def test_dockerfile_is_multistage_slim_nonroot_with_healthcheck():
    stages = dockerfile_stages()
    assert len(stages) >= 2 and " AS builder" in stages[0][0]
    builder, final = stages[0][1], stages[-1]
    assert "slim" in final[0] and "AS" not in final[0].upper().split()[2:3]
    assert any("pip wheel --no-deps" in i for i in builder)
    body = final[1]
    users = [i.split()[1] for i in body if i.startswith("USER ")]
    assert users and users[-1] not in ("root", "0")
    assert any(i.startswith("HEALTHCHECK") and "/healthz" in i for i in body)
    assert exec_form(next(i for i in body if i.startswith("CMD")))[:2] == ["bubsub", "serve"]
    installs = " ".join(i for i in body if i.startswith("RUN"))
    # only the builder's environment comes in: nothing is downloaded or compiled in the final stage
    assert any(i.startswith("COPY --from=builder /opt/bubsub ") for i in body)
    assert "pip install" not in installs
    for tool in ("gcc", "build-essential", "apt-get install", "COPY core", "COPY service"):
        assert tool not in installs and not any(i.startswith(f"COPY {tool[5:]}") for i in body if tool.startswith("COPY")), tool


def test_dockerfile_builds_with_the_classic_builder():
    # Debian's docker has no BuildKit: no parser directives, no RUN --mount
    text = (DOCKER / "Dockerfile").read_text()
    assert not re.search(r"^#\s*syntax\s*=", text, re.M | re.I)
    assert "--mount" not in text
    # the classic builder reads the context's ignore file at the root only
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert {".venv", ".git", "tests"} <= set(ignored)


def test_compose_file_is_valid_with_documented_services():
    compose = yaml.safe_load((DOCKER / "docker-compose.yml").read_text())
    assert "name" not in compose  # docker-compose v1 refuses a top-level name
    services = compose["services"]
    assert set(services) >= {"projector", "client", "scheduler", "worker", "cluster-client"}
    for svc in services.values():  # published ports on the loopback only
        assert all(str(p).startswith("127.0.0.1:") for p in svc.get("ports", [])), svc.get("ports")
    projector, client = services["projector"], services["client"]
    assert projector["build"]["dockerfile"] == "docker/Dockerfile" and projector["build"]["context"] == ".."
    env = projector["environment"]
    fields = set(Settings.model_fields)
    for key in env:
        assert key.startswith("BUBSUB_") and key[7:].lower() in fields, key
    assert env["BUBSUB_SCAN_DIR"] == "/scans"
    assert any(str(v).endswith(":/scans:ro") for v in projector["volumes"])
    assert any(p.endswith(":8000") for p in projector["ports"]) and "/healthz" in " ".join(projector["healthcheck"]["test"])
    assert projector["build"]["network"] == "host"
    assert client["depends_on"]["projector"]["condition"] == "service_healthy"
    assert client["environment"]["BUBSUB_SERVER"] == "http://projector:8000"
    script = next(a for a in client["command"] if a.endswith(".py"))
    mount = next(v for v in client["volumes"] if v.split(":")[1] == str(Path(script).parent))
    assert (DOCKER / mount.split(":")[0] / Path(script).name).resolve().is_file()


def test_compose_dask_services_share_one_scheduler_and_volume():
    services = yaml.safe_load((DOCKER / "docker-compose.yml").read_text())["services"]
    sched, worker, cc = services["scheduler"], services["worker"], services["cluster-client"]
    assert sched["command"][:2] == ["dask", "scheduler"] and "8786" in sched["command"]
    assert worker["command"][:3] == ["dask", "worker", "tcp://scheduler:8786"]
    assert worker["environment"]["BUBSUB_THREADS"] == "1" and worker["depends_on"]["scheduler"]["condition"] == "service_healthy"
    assert cc["environment"]["DASK_SCHEDULER_ADDRESS"] == "tcp://scheduler:8786"
    assert "data:/data" in worker["volumes"] and "data:/data" in cc["volumes"]
    script = next(a for a in cc["command"] if a.startswith("/examples/"))
    assert (ROOT / "examples" / Path(script).name).is_file()


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def serve_the_wheel(tmp_path):
    """Build the wheel, install it alone into a fresh venv under ``tmp_path``, serve and health-check it."""
    # 1. build the wheel exactly as the builder stage does (offline: no build isolation)
    src = tmp_path / "src"
    src.mkdir()
    shutil.copy(ROOT / "pyproject.toml", src)
    if (ROOT / "README.md").exists():
        shutil.copy(ROOT / "README.md", src)
    else:  # pragma: no cover - until the README lands
        (src / "README.md").write_text("# bubsub\n")
    for pkg in ("core", "service", "clients", "bench"):
        shutil.copytree(ROOT / pkg, src / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    dist = tmp_path / "dist"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                    "-q", "-w", str(dist), str(src)], check=True, capture_output=True)
    wheel = next(dist.glob("bubsub-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    for needed in ("bubsub/service/app.py", "bubsub/service/routes/compute.py", "bubsub/service/cli.py",
                   "bubsub/clients/remote/client.py", "bubsub/core/projection/projector.py"):
        assert needed in names, needed
    assert not any(n.startswith(("core/", "service/", "tests/")) for n in names)  # only under bubsub/

    # 2. a fresh venv with only the wheel (dependencies: this environment's, via a .pth file)
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False, system_site_packages=False).create(env_dir)
    py = env_dir / "bin" / "python"
    subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index", "-q",
                    str(wheel)], check=True, capture_output=True)
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          check=True, capture_output=True, text=True).stdout.strip()
    deps = sysconfig.get_paths()["purelib"]
    Path(site, "_bubsub_test_deps.pth").write_text(deps + "\n")  # appended after the venv's own packages
    where = subprocess.run([str(py), "-c", "import bubsub.service.app as a; print(a.__file__)"],
                           check=True, capture_output=True, text=True, cwd=tmp_path).stdout.strip()
    assert where.startswith(site), where  # the installed wheel, not the source tree

    # 3. run the image's CMD from the venv and health-check it with the image's HEALTHCHECK
    final = dockerfile_stages()[-1][1]
    cmd = exec_form(next(i for i in final if i.startswith("CMD")))
    health = exec_form(next(i for i in final if i.startswith("HEALTHCHECK")))
    if not (ROOT / "clients" / "cli.py").exists():  # pragma: no cover - until the CLI lands
        cmd = ["python", "-m", "bubsub.service"]
    port = _free_port()
    env = {**os.environ, "PATH": f"{env_dir / 'bin'}{os.pathsep}{os.environ['PATH']}",
           "BUBSUB_HOST": "127.0.0.1", "BUBSUB_PORT": str(port), "BUBSUB_LOG_LEVEL": "warning"}
    env.pop("PYTHONPATH", None)
    exe = shutil.which(cmd[0], path=env["PATH"])
    assert exe and exe.startswith(str(env_dir)), exe
    proc = subprocess.Popen([exe, *cmd[1:]], env=env, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        end = time.monotonic() + 120  # a fresh install compiles its kernels first: over a minute on a busy machine
        while True:
            probe = subprocess.run([str(py) if health[0] == "python" else health[0], *health[1:]], env=env,
                                   cwd=tmp_path, capture_output=True)
            if probe.returncode == 0:
                break
            assert proc.poll() is None, proc.stdout.read().decode()
            assert time.monotonic() < end, probe.stderr.decode()
            time.sleep(0.2)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/readyz", timeout=5) as r:
            assert json.load(r)["status"] == "ready"
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:  # pragma: no cover
            proc.kill()
    assert proc.returncode in (0, -15), proc.stdout.read().decode()


def _serve_the_wheel_run(tmp):
    # a fresh install compiles the projection kernels before it is ready: most of this test's time
    return [sys.executable, __file__, str(tmp)], None, ROOT


@pytest.mark.background(command=_serve_the_wheel_run)
def test_wheel_installs_in_a_fresh_venv_and_serves(background):
    res = background.wait(600)
    assert res.returncode == 0 and "served" in res.stdout, res.stdout[-2000:] + res.stderr[-4000:]


if __name__ == "__main__":
    serve_the_wheel(Path(sys.argv[1]))
    print("served")
