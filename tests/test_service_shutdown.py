"""Graceful shutdown of a real server process: readiness turns false first, in-flight work finishes."""

import io
import os
import signal
import subprocess
import sys
import threading
import time

import httpx
import numpy as np
import pytest

from bubsub.clients.remote.client import ProjectorClient
from bubsub.core import MeshProjector, ScanGeometry, sphere_surface
from service_support import free_socket


def test_sigterm_not_ready_first_then_drains():
    sock = free_socket()
    port = sock.getsockname()[1]
    sock.close()
    # the slower ray-casting backend and 6 x 6 sub-rays keep one call busy past the grace period
    env = {**os.environ, "BUBSUB_BACKEND": "embreex", "BUBSUB_SHUTDOWN_GRACE_SECONDS": "1.0", "BUBSUB_WORKERS": "1", "BUBSUB_LOG_LEVEL": "warning",
           "BUBSUB_JOB_COMPUTE_MAX_BYTES": str(3 << 30)}  # 6 x 6 sub-rays are over the default estimate
    proc = subprocess.Popen([sys.executable, "-m", "bubsub.service", "--host", "127.0.0.1", "--port", str(port)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        with ProjectorClient(url) as c:
            c.wait_ready(30)
            g = ScanGeometry.cone(np.linspace(0, 2 * np.pi, 96, endpoint=False), source_origin=150.0,
                                  origin_detector=50.0, pixel_size=0.3, cols=96, rows=96)
            s = [sphere_surface((-3.0, 0.0, 1.0), 4.0, 1.0), sphere_surface((4.0, 2.0, -1.0), 3.0, 1.0)]
            job = c.create_job(g, data=np.zeros(g.shape, np.float32), surfaces=s, supersampling=6)
            expected = MeshProjector(g, supersampling=6, backend="embreex").objective(s, np.zeros(g.shape, np.float32))[0]

            result = {}

            body = io.BytesIO()
            np.save(body, np.concatenate([x.vertices for x in s]))

            def slow_call():  # no retries: this very request must be answered
                r = httpx.post(f"{url}/v1/jobs/{job.job_id}/objective", content=body.getvalue(),
                               headers={"content-type": "application/x-npy"}, timeout=60)
                result["status"] = r.status_code
                result["f"] = float(r.headers["x-objective"])
                result["done"] = time.monotonic()

            t = threading.Thread(target=slow_call)
            t.start()
            time.sleep(0.3)  # the call is computing now
            t0 = time.monotonic()
            proc.send_signal(signal.SIGTERM)
            saw_not_ready = False
            while time.monotonic() - t0 < 0.9:
                r = httpx.get(f"{url}/readyz", timeout=2)
                if r.status_code == 503:
                    saw_not_ready = True
                    assert httpx.get(f"{url}/healthz", timeout=2).status_code == 200
                    break
                time.sleep(0.05)
            assert saw_not_ready, "readiness did not turn false after SIGTERM"
            t.join(60)
            assert result["status"] == 200 and result["f"] == pytest.approx(expected, rel=1e-9)  # finished ...
            assert result["done"] > t0 + 1.0  # ... after the grace period, i.e. while the server drained
        assert proc.wait(30) in (0, -signal.SIGTERM)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_computation_cancelled_by_the_shutdown_timeout_answers_503_retry_after():
    """Issue 13: when the shutdown timeout expired, in-flight computations got 500 (not retried)."""
    from bubsub.bench.attacks import ATTACKS, shutdown_timeout
    from bubsub.bench.service_harness import ServerProcess

    env = ATTACKS["shutdown_timeout"][1]
    with ServerProcess(**env) as srv, httpx.Client(timeout=60) as h:
        (result,), _ = shutdown_timeout(srv, h)
        assert result == "503 Retry-After 1", result
        # the process itself exits once the running computation ends (threads cannot be killed); not waited for
        srv.proc.kill()
