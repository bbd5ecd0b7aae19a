"""Slow clients: header and body timeouts, and a free event loop (the connection limit: test_service_connections).

Issue 13: with no header/body timeout, slow connections held the server; one 21 MiB .npz with
95,000 members stalled /healthz for 9 s because bodies were decoded on the event loop. Issue 30: a
body that no route reads could trickle in for ever.
"""

import threading
import time

import httpx
import pytest

from bubsub.bench.service_harness import raw_request, read_until_closed
from service_support import ServerThread


SLOW_HEAD = b"GET /healthz HTTP/1.1\r\nHost: x\r\n"  # no blank line: the head never ends


@pytest.fixture(scope="module")
def srv():
    with ServerThread(header_timeout_seconds=0.5, body_timeout_seconds=0.5, max_connections=20) as s:
        yield s


def test_incomplete_request_head_is_closed_after_the_header_timeout(srv):
    with raw_request(srv.port, SLOW_HEAD) as s:
        t0 = time.monotonic()
        assert s.recv(100) == b""  # closed by the server ...
        assert time.monotonic() - t0 < 3  # ... after about 0.5 s
    assert srv.state.requests.refused.get("header_timeout", 0) >= 1


def test_slow_body_gets_408(srv):
    with raw_request(srv.port, b"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                         b"Content-Length: 100\r\n\r\n{\"geo") as s:
        reply = read_until_closed(s)
    assert reply.startswith(b"HTTP/1.1 408") and b"BUBSUB_BODY_TIMEOUT_SECONDS" in reply


def test_body_that_no_route_reads_is_cut_off_too(srv):
    """/healthz answers without reading a body; the rest of it may not trickle in for ever."""
    before = srv.state.requests.refused.get("body_timeout", 0)
    with raw_request(srv.port, b"GET /healthz HTTP/1.1\r\nHost: x\r\nContent-Length: 1000\r\n\r\nab") as s:
        t0 = time.monotonic()
        reply = b""
        while True:
            chunk = s.recv(4096)
            if not chunk:
                break
            reply += chunk
            s.sendall(b"x")  # a byte now and then: uvicorn's keep-alive timer restarts at each
        took = time.monotonic() - t0
    assert reply.startswith(b"HTTP/1.1 200")
    assert 1.0 < took < 5, took  # the body timeout (0.5 s) and its grace (1 s)
    assert srv.state.requests.refused.get("body_timeout", 0) == before + 1


def test_decoding_runs_off_the_event_loop():
    """/healthz answers promptly while large job bodies are parsed."""
    import json

    from bubsub.bench.service_harness import sphere_job

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
