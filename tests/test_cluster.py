"""The cluster engine: in-process by default (no Dask imported), an embedded LocalCluster,
and an existing cluster reached by --scheduler-file; all give the in-process results.

Everything listens on 127.0.0.1 only, with 1 thread per worker; each run is a couple of
quick voxel-baseline cases of ``bubsub experiment`` so that the tests stay short.
"""

import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bubsub.clients.cli.main import main
from bubsub.clients.cluster import engine
from bubsub.clients.cluster.engine import (from_scheduler_file, in_process, local, open_client, remote, run_tasks,
                                           spec_from_options)

# fig1a at 10 views with two voxel baselines: two real tasks of a few seconds each
CASE = ["experiment", "fig1a", "--quick", "--values", "10", "--methods", "fbp", "sirt", "--quiet"]


def ddis(out):
    with open(Path(out) / "fig1a.csv") as f:
        return {(r["angles"], r["method"], r["seed"]): float(r["ddi"]) for r in csv.DictReader(f)}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The in-process results, from a fresh interpreter that must not import Dask on the way."""
    out = tmp_path_factory.mktemp("in-process")
    code = ("import sys\nfrom bubsub.clients.cli.main import main\n"
            f"assert main({[*CASE, '--out', str(out)]!r}) == 0\n"
            "print(sorted(m for m in sys.modules if m == 'dask' or m.startswith(('dask.', 'distributed'))))\n")
    env = {k: v for k, v in os.environ.items() if k != "DASK_SCHEDULER_ADDRESS"}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=240)
    assert res.returncode == 0, res.stderr
    return ddis(out), res.stdout.strip().splitlines()[-1]


def test_specs_from_options_and_environment(tmp_path):
    assert spec_from_options(environ={}) == in_process() and in_process().in_process
    assert spec_from_options(workers=3, environ={}) == local(3)
    assert repr(local(3)) == "local(3)" and repr(local(2, threads=2, dashboard=True)) == "local(2, threads=2, dashboard=True)"
    assert spec_from_options(environ={"DASK_SCHEDULER_ADDRESS": "tcp://10.0.0.1:8786"}) == remote("tcp://10.0.0.1:8786")
    # an explicit option wins over the environment
    assert spec_from_options(workers=2, environ={"DASK_SCHEDULER_ADDRESS": "tcp://10.0.0.1:8786"}).kind == "local"
    f = tmp_path / "scheduler.json"
    f.write_text("{}")
    assert spec_from_options(scheduler_file=str(f), environ={}) == from_scheduler_file(f)
    assert repr(from_scheduler_file(f)) == f"from_scheduler_file({str(f)!r})"
    with pytest.raises(ValueError, match="only one of --workers, --scheduler"):
        spec_from_options(workers=2, scheduler="tcp://a:1", environ={})
    with pytest.raises(ValueError, match="tcp://HOST:PORT"):
        remote("10.0.0.1:8786")
    with pytest.raises(FileNotFoundError, match="dask scheduler --scheduler-file"):
        from_scheduler_file(tmp_path / "missing.json")
    with pytest.raises(ValueError, match="--dashboard"):
        spec_from_options(dashboard=True, environ={})


def test_cli_refuses_two_cluster_options(tmp_path, capsys):
    assert main([*CASE, "--out", str(tmp_path), "--workers", "2", "--scheduler", "tcp://127.0.0.1:1"]) == 2
    assert "give only one of --workers, --scheduler" in capsys.readouterr().err
    assert not (tmp_path / "fig1a.csv").exists()


def test_missing_dask_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "dask.distributed", None)  # as if not installed
    with pytest.raises(ImportError, match=r"pip install 'bubsub\[cluster\]'"):
        with open_client(local(1)):
            pass


def test_default_path_does_not_import_dask(reference):
    results, dask_modules = reference
    assert dask_modules == "[]"
    assert len(results) == 2 and all(0 <= v <= 1 for v in results.values())


def test_projector_threads_follow_bubsub_threads(monkeypatch):
    from bubsub.core.projection.projector import default_threads

    monkeypatch.setenv("BUBSUB_THREADS", "3")
    assert default_threads() == 3
    monkeypatch.setenv("BUBSUB_THREADS", "0")
    with pytest.raises(ValueError, match="BUBSUB_THREADS must be a positive integer"):
        default_threads()


def test_run_tasks_keeps_task_order_and_reports_each_result():
    seen = []
    assert run_tasks(None, pow, [(2, 3), (3, 2)], on_result=lambda i, r: seen.append((i, r))) == [8, 9]
    assert seen == [(0, 8), (1, 9)]


def test_embedded_cluster_gives_the_in_process_results(tmp_path, reference):
    t = time.perf_counter()
    with open_client(local(2)) as client:
        assert engine.workers_of(client) == 2
        # workers are pinned to one thread for the projector, numba and BLAS
        envs = client.run(lambda: {k: os.environ.get(k) for k in ("BUBSUB_THREADS", "NUMBA_NUM_THREADS")})
        assert all(e == {"BUBSUB_THREADS": "1", "NUMBA_NUM_THREADS": "1"} for e in envs.values())
        assert all(a.startswith("tcp://127.0.0.1:") for a in envs)
        from bubsub.clients.experiments.runner import run_experiment

        run_experiment("fig1a", tmp_path, quick=True, values=[10], methods=["fbp", "sirt"], progress=False,
                       client=client)
    assert ddis(tmp_path) == reference[0]
    assert time.perf_counter() - t < 240


def _start(args, log):
    return subprocess.Popen([sys.executable, "-m", *args], stdout=log, stderr=subprocess.STDOUT,
                            env={**os.environ, "BUBSUB_THREADS": "1"})


def test_existing_cluster_by_scheduler_file(tmp_path, reference):
    sfile = tmp_path / "scheduler.json"
    log = open(tmp_path / "cluster.log", "w")
    procs = [_start(["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                     "--scheduler-file", str(sfile)], log)]
    try:
        end = time.monotonic() + 60
        while not (sfile.exists() and sfile.stat().st_size):
            assert procs[0].poll() is None and time.monotonic() < end, (tmp_path / "cluster.log").read_text()
            time.sleep(0.2)
        assert json.loads(sfile.read_text())["address"].startswith("tcp://127.0.0.1:")
        procs.append(_start(["distributed.cli.dask_worker", "--scheduler-file", str(sfile), "--nthreads", "1",
                             "--host", "127.0.0.1", "--no-dashboard"], log))
        out = tmp_path / "out"
        assert main([*CASE, "--out", str(out), "--scheduler-file", str(sfile)]) == 0
        assert ddis(out) == reference[0]
        # the cases ran as tasks on that cluster's worker, not here
        with open_client(from_scheduler_file(sfile)) as client:
            prefixes = client.run_on_scheduler(lambda dask_scheduler: sorted(dask_scheduler.task_prefixes))
            assert "run_setting" in prefixes
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:  # pragma: no cover
                p.kill()
        log.close()


def test_slurm_job_script_runs_pinned_bubsub_workers(tmp_path):
    from bubsub.clients.cluster.hpc import slurm_cluster

    cluster = slurm_cluster(workers_per_job=4, threads=2, memory="16GB", walltime="02:30:00", queue="short",
                            account="foam", prologue=["source /opt/bubsub/bin/activate"], directives=["--exclusive"],
                            log_directory=str(tmp_path), scheduler_options={"host": "127.0.0.1", "dashboard_address": None})
    try:
        script = cluster.job_script()
    finally:
        cluster.close()
    lines = script.splitlines()
    for directive in ("#SBATCH -p short", "#SBATCH -A foam", "#SBATCH --cpus-per-task=8", "#SBATCH -t 02:30:00",
                      "#SBATCH --exclusive"):
        assert directive in lines, directive
    assert any(l.startswith("#SBATCH --mem=") and l.endswith("G") for l in lines)
    exports = [l for l in lines if l.startswith("export ")]
    assert "export BUBSUB_THREADS=2" in exports and "export NUMBA_NUM_THREADS=2" in exports
    worker = next(l for l in lines if "dask_worker" in l)
    # the exports and the environment come before the worker starts
    assert lines.index(exports[0]) < lines.index("source /opt/bubsub/bin/activate") < lines.index(worker)
    assert "tcp://127.0.0.1:" in worker and "--nworkers 4" in worker and "--nthreads 2" in worker


def test_slurm_cluster_refuses_bad_sizes():
    from bubsub.clients.cluster.hpc import slurm_cluster

    with pytest.raises(ValueError, match="workers_per_job must be a positive integer"):
        slurm_cluster(workers_per_job=0)
