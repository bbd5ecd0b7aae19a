"""Slow clients and decoding: header/body timeouts, the connection limit, and a free event loop.

Issue 13: with no header/body timeout and no concurrency limit, 300 slow connections
starved every normal request; one 21 MiB .npz with 95,000 members stalled /healthz
for 9 s because bodies were decoded on the event loop.
"""

import socket
import threading
import time

import httpx
import pytest

from service_support import ServerThread


@pytest.fixture(scope="module")
def srv():
    with ServerThread(header_timeout_seconds=0.5, body_timeout_seconds=0.5, max_connections=20) as s:
        yield s


def _slow(port, head=b"GET /healthz HTTP/1.1\r\nHost: x\r\n"):
    s = socket.create_connection(("127.0.0.1", port), timeout=5)
    s.sendall(head)
    return s


def test_incomplete_request_head_is_closed_after_the_header_timeout(srv):
    with _slow(srv.port) as s:
        t0 = time.monotonic()
        assert s.recv(100) == b""  # closed by the server ...
        assert time.monotonic() - t0 < 3  # ... after about 0.5 s
    assert srv.state.requests.refused.get("header_timeout", 0) >= 1


def test_slow_body_gets_408(srv):
    with _slow(srv.port, b"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                         b"Content-Length: 100\r\n\r\n{\"geo") as s:
        reply = b""
        while chunk := s.recv(4096):  # until the server closes the connection
            reply += chunk
    assert reply.startswith(b"HTTP/1.1 408") and b"BUBSUB_BODY_TIMEOUT_SECONDS" in reply


def test_many_slow_connections_do_not_starve_normal_requests(srv):
    slow = [_slow(srv.port) for _ in range(60)]  # three times the connection limit
    try:
        t0 = time.monotonic()
        answered = None
        while time.monotonic() - t0 < 10:
            try:
                if httpx.get(f"{srv.url}/v1/jobs", timeout=2).status_code == 200:
                    answered = time.monotonic() - t0
                    break
            except httpx.HTTPError:
                time.sleep(0.1)
        assert answered is not None and answered < 5, answered
        assert srv.state.requests.refused.get("connections", 0) >= 30
    finally:
        for s in slow:
            s.close()


def test_requests_over_the_concurrency_limit_get_503():
    with ServerThread(max_connections=3, header_timeout_seconds=10) as s:
        idle = [httpx.Client(base_url=s.url) for _ in range(3)]
        try:
            for c in idle[:2]:
                assert c.get("/healthz").status_code == 200  # two keep-alive connections stay open
            r = idle[2].get("/healthz")
            assert r.status_code == 503  # the third reaches the limit (uvicorn limit_concurrency)
        finally:
            for c in idle:
                c.close()


def test_decoding_runs_off_the_event_loop():
    """/healthz answers promptly while large job bodies are parsed."""
    import json

    from bubsub.bench.attacks import sphere_job

    spec, _ = sphere_job(8, 8)
    spec["surfaces"][0]["faces"] = spec["surfaces"][0]["faces"] * 2000  # 160,000 faces, ~2.5 MB of JSON
    body = json.dumps(spec).encode()
    worst = []

    def probe(stop):
        with httpx.Client(timeout=30) as h:
            while not stop.is_set():
                t0 = time.perf_counter()
                assert h.get(f"{srv.url}/healthz").status_code == 200
                worst.append(time.perf_counter() - t0)
                time.sleep(0.01)

    srv = ServerThread()
    stop = threading.Event()
    t = threading.Thread(target=probe, args=(stop,))
    t.start()
    try:
        t0 = time.perf_counter()
        for _ in range(3):
            r = httpx.post(f"{srv.url}/v1/jobs", content=body, headers={"content-type": "application/json"},
                           timeout=60)
            assert r.status_code == 422  # duplicate faces: an invalid mesh, found after parsing
        took = time.perf_counter() - t0
    finally:
        stop.set()
        t.join()
        srv.stop()
    assert len(worst) >= 3 and max(worst) < max(0.5, took / 3), (max(worst), took)
