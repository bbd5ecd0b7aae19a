"""The connection limit: derived from the descriptor limit, slow connections make room, every 503 has Retry-After.

Issue 30: 300 connections that never finished their request heads against a descriptor limit of 256
left /healthz unanswered for the whole attack (connections beyond the limit were closed at once,
health checks among them); a 503 at the connection limit came without Retry-After.
"""

import os
import threading
import time

import httpx

from bubsub.bench.service_harness import ServerProcess, SlowClients, probe_health, raw_request, read_until_closed
from bubsub.service.config import Settings
from bubsub.service.server import FD_RESERVE, connection_limits
from service_support import ServerThread


def test_limits_fit_the_descriptor_limit():
    settings = Settings()
    for nofile in (256, 1024, 65536):
        lim = connection_limits(settings, nofile)
        assert lim.requests + lim.health == lim.connections <= settings.max_connections
        assert lim.health >= 1 and lim.backlog <= lim.connections // 3
        # held connections, the headroom and four accept batches fit beside the descriptors open now
        open_now = len(os.listdir("/proc/self/fd"))
        assert lim.connections + lim.health + 4 * lim.backlog <= nofile - FD_RESERVE - open_now + 1
    assert connection_limits(settings, 1024).connections == settings.max_connections  # not lowered when it fits


def test_connections_waiting_for_a_head_make_room_for_new_ones():
    """Slow connections beyond the limit do not keep new ones out: the oldest waiting one is closed."""
    with ServerThread(header_timeout_seconds=30, max_connections=20) as s:
        s.sock.listen(1024)  # the kernel's queue of bubsub serve (service.server.Server)
        limits, refused = s.state.limits, s.state.requests.refused
        n = 3 * limits.connections
        with SlowClients(s.port, n, reconnect=False):
            end = time.monotonic() + 10
            while refused.get("evicted", 0) < n - limits.connections - limits.health and time.monotonic() < end:
                time.sleep(0.05)
            assert len(s.server.server_state.connections) <= limits.connections + limits.health
            assert refused.get("evicted", 0) >= n - limits.connections - limits.health
            for path in ("/v1/jobs", "/healthz", "/readyz"):
                t0 = time.monotonic()
                assert httpx.get(s.url + path, timeout=5).status_code == 200
                assert time.monotonic() - t0 < 1
        assert refused.get("header_timeout", 0) == 0  # evicted, not timed out (30 s)


def _slow_body(port, path=b"/v1/jobs"):
    return raw_request(port, b"POST " + path + b" HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                                        b"Content-Length: 100\r\n\r\n{")


def test_requests_over_the_request_limit_get_503_with_retry_after_and_health_still_answers():
    with ServerThread(max_connections=4, body_timeout_seconds=30, retry_after_seconds=2) as s:
        limits = s.state.limits
        assert (limits.connections, limits.health, limits.requests) == (4, 1, 3)
        held = [_slow_body(s.port) for _ in range(limits.requests)]  # requests in flight, reading their bodies
        try:
            time.sleep(0.3)
            r = httpx.post(f"{s.url}/v1/jobs", json={}, timeout=5)
            assert r.status_code == 503 and r.headers["retry-after"] == "2" and r.json()["code"] == "connections"
            assert "BUBSUB_MAX_CONNECTIONS" in r.json()["detail"]
            for path in ("/healthz", "/readyz", "/metrics"):  # the connections kept for monitoring
                assert httpx.get(s.url + path, timeout=5).status_code == 200
        finally:
            for c in held:
                c.close()
        assert httpx.post(f"{s.url}/v1/jobs", json={}, timeout=5).status_code == 422  # room again


def test_connection_refused_when_all_are_busy_gets_503_with_retry_after():
    with ServerThread(max_connections=2, body_timeout_seconds=30, retry_after_seconds=3) as s:
        limits = s.state.limits
        assert (limits.connections, limits.health, limits.requests) == (2, 1, 1)
        busy = [_slow_body(s.port)]  # the one request allowed, reading its body
        # two answered health checks whose bodies still trickle in: busy, not waiting for a head
        for _ in range(limits.connections + limits.health - 1):
            c = raw_request(s.port, b"GET /healthz HTTP/1.1\r\nHost: x\r\nContent-Length: 100\r\n\r\nab")
            assert c.recv(4096).startswith(b"HTTP/1.1 200")
            busy.append(c)
        try:
            with raw_request(s.port, b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n") as c:
                reply = read_until_closed(c)
            assert reply.startswith(b"HTTP/1.1 503") and b"retry-after: 3\r\n" in reply.lower()
            assert b'"code": "connections"' in reply
        finally:
            for c in busy:
                c.close()
        assert s.state.requests.refused.get("connections", 0) == 1


def test_health_answers_within_a_second_while_300_slow_clients_hold_connections_against_256_descriptors():
    with ServerProcess(nofile=256, BUBSUB_LOG_LEVEL="warning") as srv:
        with SlowClients(srv.port, 300, reconnect=False) as slow:
            time.sleep(0.5)
            normal = []

            def requests():
                end = time.monotonic() + 3
                while time.monotonic() < end:
                    r = httpx.get(f"{srv.url}/v1/jobs", timeout=5)
                    normal.append((r.status_code, r.headers.get("retry-after")))
                    time.sleep(0.1)

            t = threading.Thread(target=requests)
            t.start()
            probes = probe_health(srv.url, 4, interval=0.05)
            t.join()
            assert slow.opened == 300 and slow.closed >= 300 - 256  # most were let in, then made room
        metrics = httpx.get(f"{srv.url}/metrics", timeout=5).text
        srv.stop()
        log = srv.proc.stderr.read().decode()
    assert len(probes) >= 10 and {p for p, _, _ in probes} == {"/healthz", "/readyz"}
    assert all(status == 200 for _, status, _ in probes), probes
    assert max(dt for _, _, dt in probes) < 1.0, probes
    assert normal and all(st == 200 or (st == 503 and ra) for st, ra in normal), normal
    assert 'reason="evicted"' in metrics
    assert "out of system resource" not in log and "Too many open files" not in log, log[-2000:]
