"""Limits: body size (413), memory caps (413/507), full queue (503 + Retry-After), idle expiry."""

import io
import socket
import threading
import time

import httpx
import numpy as np
import pytest

from bubsub.clients.remote.client import ProjectorClient
from bubsub.core import MeshProjector, ScanGeometry, sphere_surface
from service_support import ServerThread, p2d  # noqa: F401 - fixture


def npy(a):
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


@pytest.fixture(scope="module")
def small():
    """A server with a 64 KiB body limit."""
    with ServerThread(max_body_bytes=64 << 10) as s:
        yield s


@pytest.fixture(scope="module")
def capped():
    """A server with jobs capped at 250 kB each and 300 kB in all (computations: 10 MB)."""
    with ServerThread(job_max_bytes=250_000, max_memory_bytes=300_000, job_compute_max_bytes=10_000_000) as s:
        yield s


def test_oversized_body_413_by_content_length(small, p2d):  # noqa: F811
    job = ProjectorClient(small.url).create_job(p2d.geometry, surfaces=p2d.init)
    r = httpx.put(f"{small.url}/v1/jobs/{job.id}/data", content=b"\0" * (100 << 10),
                  headers={"content-type": "application/x-npy"})
    assert r.status_code == 413 and r.json()["code"] == "too_large"
    assert "BUBSUB_MAX_BODY_BYTES" in r.json()["detail"]


def test_oversized_chunked_body_413_while_streaming(small):
    def chunks():
        for _ in range(40):
            yield b"\0" * 4096  # 160 KiB without a Content-Length

    r = httpx.post(f"{small.url}/v1/jobs", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 413 and r.json()["code"] == "too_large"


def test_oversized_declared_length_refused_before_the_body(small):
    """413 arrives although the body was never sent: the server did not wait for it."""
    with socket.create_connection(("127.0.0.1", small.port), timeout=5) as sock:
        sock.sendall(b"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                     b"Content-Length: 999999999\r\n\r\n")
        reply = sock.recv(4096)
    assert reply.startswith(b"HTTP/1.1 413")


def test_memory_caps_413_per_job_and_507_server_wide(capped):
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 50, endpoint=False), cols=500)  # 100 kB projections
    from bubsub.core import circle_surface

    s = [circle_surface((0, 0), 50, 1.0)]
    data = np.zeros(g.shape, np.float32)
    with ProjectorClient(capped.url, retry_timeout=5) as c:
        with pytest.raises(ValueError, match="per-job cap") as e:  # data + background + target: 300 kB
            c.create_job(g, data=data, background=data, surfaces=s)
        assert e.value.status == 413
        a = c.create_job(g, data=data, surfaces=s)
        b = c.create_job(g, data=data, surfaces=s)
        with pytest.raises(Exception, match="BUBSUB_MAX_MEMORY_BYTES") as e:
            c.create_job(g, data=data, surfaces=s)
        assert e.value.status == 507
        with pytest.raises(Exception, match="cap") as e:  # an upload counts too
            a.set_background(data)
        assert e.value.status in (413, 507)
        b.delete()
        c.create_job(g, data=data, surfaces=s).delete()  # room again
        a.delete()


def heavy_job(url):
    g = ScanGeometry.cone(np.linspace(0, 2 * np.pi, 24, endpoint=False), source_origin=150.0,
                          origin_detector=50.0, pixel_size=0.4, cols=64, rows=64)
    s = [sphere_surface((-3.0, 0.0, 1.0), 4.0, 1.0), sphere_surface((4.0, 2.0, -1.0), 3.0, 1.0)]
    data = MeshProjector(g, supersampling=2).forward(s)
    with ProjectorClient(url) as c:
        job = c.create_job(g, data=data, surfaces=s, supersampling=2)
    return job, s


def test_full_queue_answers_503_with_retry_after():
    with ServerThread(workers=1, max_queue=1, retry_after_seconds=1) as s:
        job, surfaces = heavy_job(s.url)
        body = npy(np.concatenate([x.vertices for x in surfaces]))
        barrier = threading.Barrier(6)
        replies = []

        def hit():
            with httpx.Client(timeout=60) as h:
                barrier.wait()
                replies.append(h.post(f"{s.url}/v1/jobs/{job.id}/objective", content=body,
                                      headers={"content-type": "application/x-npy"}))

        threads = [threading.Thread(target=hit) for _ in range(6)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        codes = sorted(r.status_code for r in replies)
        assert codes.count(200) >= 2 and codes.count(503) >= 1, codes  # one ran, one waited, others refused
        busy = [r for r in replies if r.status_code == 503]
        assert all(r.headers["retry-after"] == "1" and r.json()["code"] == "busy" for r in busy)
        assert s.state.pool.rejected_total == len(busy)

        # the client retries 503 with backoff: all six calls succeed
        job.client = ProjectorClient(s.url, retry_timeout=60, backoff=0.05)
        values = []
        threads = [threading.Thread(target=lambda: values.append(job.objective(surfaces)[0])) for _ in range(6)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert len(values) == 6 and len(set(values)) == 1


def test_idle_jobs_expire():
    from service_support import phantom_2d

    from bubsub.core import MeshProjector

    p = phantom_2d()
    # compile the projector's kernels for these arrays first (a cold numba cache takes longer than the TTL)
    for dtype in (np.float32, np.float64):
        MeshProjector(p.geometry).objective(p.init, p.data.astype(dtype))
    # uses 0.2 s apart keep it alive past its 1 s TTL (0.8 s of slack for a busy machine); then 2 s idle expire it
    with ServerThread(job_ttl_seconds=1.0, sweep_interval_seconds=0.05) as s:
        with ProjectorClient(s.url) as c:
            job = c.create_job(p.geometry, data=p.data, surfaces=p.init)
            for _ in range(8):
                time.sleep(0.2)
                job.objective(p.init)
            time.sleep(2.0)
            r = httpx.get(f"{s.url}/v1/jobs/{job.id}")
            assert r.status_code == 404 and r.json()["code"] == "unknown_job"
            assert s.state.store.expired_total == 1 and len(s.state.store) == 0
            assert "bubsub_jobs_expired_total 1" in httpx.get(f"{s.url}/metrics").text
            job.objective(p.init)  # the client re-creates it
            assert job.recreated == 1
