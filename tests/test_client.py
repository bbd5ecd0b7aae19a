"""ProjectorClient / RemoteJob: remote fits equal local ones, run concurrently, and survive restarts."""

import threading
import time

import numpy as np
import pytest

from bubsub.clients.remote.client import ProjectorClient, RemoteError, UnknownJobError
from bubsub.clients.optimise.fit import fit
from service_support import ServerThread, client, p2d, phantom_2d, server  # noqa: F401 - fixtures

ITER = 25


def _vertices(surfaces):
    return np.concatenate([s.vertices for s in surfaces])


def assert_recovered(result, phantom):
    """Fitted bubbles match the truth: areas within 5 %, centroids within 0.2 mm (2/3 pixel)."""
    for got, want in zip(result.surfaces, phantom.truth):
        assert got.fine().area == pytest.approx(want.fine().area, rel=0.05)
        assert np.linalg.norm(got.fine().centroid - want.fine().centroid) < 0.2


def test_remote_fit_equals_local_fit(client, p2d):  # noqa: F811
    local = fit(p2d.projector, p2d.init, p2d.data, iterations=ITER, progress=False)
    with client.create_job(p2d.geometry, data=p2d.data, surfaces=p2d.init) as job:
        remote = fit(job, p2d.init, iterations=ITER, progress=False)
    assert remote.iterations == local.iterations and remote.objective == pytest.approx(local.objective, rel=1e-9)
    np.testing.assert_allclose(_vertices(remote.surfaces), _vertices(local.surfaces), rtol=0, atol=1e-9)
    assert_recovered(remote, p2d)


def test_four_concurrent_fits_each_correct_none_starved(server, p2d):  # noqa: F811
    phantoms = [phantom_2d(shift=s) for s in (-2.0, -1.0, 1.0, 2.0)]
    expected = [fit(p.projector, p.init, p.data, iterations=ITER, progress=False) for p in phantoms]
    results, spans, errors = [None] * 4, [None] * 4, []
    barrier = threading.Barrier(4)

    def worker(k):
        try:
            with ProjectorClient(server.url) as c:
                job = c.create_job(phantoms[k].geometry, data=phantoms[k].data, surfaces=phantoms[k].init)
                barrier.wait()
                t0 = time.perf_counter()
                results[k] = fit(job, phantoms[k].init, iterations=ITER, progress=False)
                spans[k] = (t0, time.perf_counter())
                job.delete()
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert not errors, errors
    for got, want, p in zip(results, expected, phantoms):
        np.testing.assert_allclose(_vertices(got.surfaces), _vertices(want.surfaces), rtol=0, atol=1e-9)
        assert_recovered(got, p)
    # none starved: the four fits overlapped in time and took comparable wall time
    assert max(s for s, _ in spans) < min(e for _, e in spans)
    durations = [e - s for s, e in spans]
    assert max(durations) < 3 * min(durations), durations


def test_a_fit_survives_a_server_restart(p2d):  # noqa: F811
    first = ServerThread()
    port = first.port
    holder = {"server": first}

    def restart(iteration, f, surfaces):
        if iteration == 5:
            holder["server"].stop()  # the jobs are gone with it ...

            def later():  # ... and the new server comes up a little later, on the same port
                time.sleep(0.3)
                holder["server"] = ServerThread(port=port)

            threading.Thread(target=later).start()
        return False

    local = fit(p2d.projector, p2d.init, p2d.data, iterations=ITER, progress=False)
    with ProjectorClient(first.url, retry_timeout=30) as c:
        job = c.create_job(p2d.geometry, data=p2d.data, surfaces=p2d.init)
        old = job.job_id
        remote = fit(job, p2d.init, iterations=ITER, progress=False, callback=restart)
        assert job.recreated == 1 and job.job_id != old
        np.testing.assert_allclose(_vertices(remote.surfaces), _vertices(local.surfaces), rtol=0, atol=1e-9)
    holder["server"].stop()


def test_unknown_job_and_unreachable_server_errors(p2d):  # noqa: F811
    s = ServerThread()
    with ProjectorClient(s.url, retry_timeout=0.3) as c:
        with pytest.raises(UnknownJobError):
            c.request("GET", "/v1/jobs/nope")
        job = c.create_job(p2d.geometry, data=p2d.data, surfaces=p2d.init)
        s.stop()
        with pytest.raises(RemoteError, match="gave up") as e:  # server gone for good: retries end
            job.objective(p2d.init)
        assert e.value.status == 0


def test_example_remote_fit_runs_against_a_server(server):  # noqa: F811
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "examples" / "remote_fit.py"
    out = subprocess.run([sys.executable, str(script), "--server", server.url, "--iterations", "8"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "largest relative area error" in out.stdout
