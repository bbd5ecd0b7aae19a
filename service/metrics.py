"""Prometheus metrics in the text exposition format (no client library needed).

:class:`RequestMetrics` is filled by :class:`MetricsMiddleware` (requests by
method, route template and status; time spent); :func:`render` adds the job
store, the compute pool and the process memory at scrape time.
"""

from __future__ import annotations

import os
import time

__all__ = ["RequestMetrics", "MetricsMiddleware", "render", "CONTENT_TYPE"]

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


#: method label values; any other method is counted as ``other`` (labels must not grow with client input)
METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "DELETE", "OPTIONS", "PATCH"})


class RequestMetrics:
    """HTTP request counters."""

    def __init__(self):
        self.requests = {}  # (method, route, status) -> count
        self.seconds = {}  # (method, route) -> total seconds
        self.refused = {}  # reason (an error code of the server's own) -> count
        self.in_flight = 0

    def refuse(self, reason):
        """Count a request refused for ``reason`` (a limit, quota or timeout)."""
        self.refused[reason] = self.refused.get(reason, 0) + 1

    def observe(self, method, route, status, seconds):
        method = method if method in METHODS else "other"
        status = int(status) if 100 <= int(status) <= 599 else 0
        key = (method, route, str(status))
        self.requests[key] = self.requests.get(key, 0) + 1
        k2 = (method, route)
        self.seconds[k2] = self.seconds.get(k2, 0.0) + seconds


class MetricsMiddleware:
    """Count every HTTP request by route template (never by raw path: job ids are secret)."""

    def __init__(self, app, metrics):
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        status = [500]

        async def send_wrapper(message):
            if message["type"] == "http.response.start":
                status[0] = message["status"]
            await send(message)

        t0 = time.perf_counter()
        self.metrics.in_flight += 1
        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            self.metrics.in_flight -= 1
            route = scope.get("route")
            path = getattr(route, "path", None) or "unmatched"
            self.metrics.observe(scope.get("method", ""), path, status[0], time.perf_counter() - t0)


def resident_memory_bytes():
    """Resident set size of this process (0 where unknown)."""
    try:
        with open("/proc/self/statm", "rb") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        try:
            import resource

            return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
        except Exception:  # pragma: no cover - no resource module
            return 0


def _escape(value):
    return str(value).replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _labels(**labels):
    if not labels:
        return ""
    return "{" + ",".join(f'{k}="{_escape(v)}"' for k, v in labels.items()) + "}"


def render(requests, store, pool, ready, settings):
    """The ``/metrics`` page.

    Parameters
    ----------
    requests : RequestMetrics
    store : JobStore
    pool : ComputePool
    ready : bool
    settings : Settings

    Returns
    -------
    str
    """
    out = []

    def metric(name, kind, help_, samples):
        out.append(f"# HELP {name} {help_}")
        out.append(f"# TYPE {name} {kind}")
        for labels, value in samples:
            out.append(f"{name}{_labels(**labels)} {value!r}" if isinstance(value, float)
                       else f"{name}{_labels(**labels)} {value}")

    metric("bubsub_http_requests_total", "counter", "HTTP requests by method, route template and status.",
           [({"method": m, "route": r, "status": s}, n) for (m, r, s), n in sorted(requests.requests.items())])
    metric("bubsub_http_request_seconds_total", "counter", "Time spent answering HTTP requests.",
           [({"method": m, "route": r}, float(t)) for (m, r), t in sorted(requests.seconds.items())])
    metric("bubsub_requests_refused_total", "counter",
           "Requests refused by a limit, quota or timeout, by reason (the error code).",
           [({"reason": r}, n) for r, n in sorted(requests.refused.items())])
    metric("bubsub_http_requests_in_flight", "gauge", "HTTP requests being answered.", [({}, requests.in_flight)])
    metric("bubsub_jobs", "gauge", "Jobs held.", [({}, len(store))])
    metric("bubsub_jobs_created_total", "counter", "Jobs created.", [({}, store.created_total)])
    metric("bubsub_jobs_deleted_total", "counter", "Jobs deleted by clients.", [({}, store.deleted_total)])
    metric("bubsub_jobs_expired_total", "counter", "Jobs removed after being idle.", [({}, store.expired_total)])
    metric("bubsub_job_memory_bytes", "gauge", "Bytes held by the jobs' arrays.", [({}, store.memory_bytes)])
    metric("bubsub_job_memory_limit_bytes", "gauge", "Server-wide cap on the jobs' arrays.",
           [({}, settings.max_memory_bytes)])
    metric("bubsub_process_resident_memory_bytes", "gauge", "Resident memory of the server process.",
           [({}, resident_memory_bytes())])
    metric("bubsub_compute_seconds_total", "counter", "Time spent computing, by operation.",
           [({"op": op}, float(t)) for op, t in sorted(pool.seconds.items())])
    metric("bubsub_compute_calls_total", "counter", "Computations finished, by operation.",
           [({"op": op}, n) for op, n in sorted(pool.calls.items())])
    metric("bubsub_compute_running", "gauge", "Computations running.", [({}, pool.running)])
    metric("bubsub_compute_queued", "gauge", "Computations waiting for a worker.", [({}, pool.queued)])
    metric("bubsub_compute_workers", "gauge", "Computations allowed at once.", [({}, pool.workers)])
    metric("bubsub_compute_rejected_total", "counter", "Computations refused with 503 (queue, quota, budget).",
           [({}, pool.rejected_total)])
    metric("bubsub_compute_cancelled_total", "counter", "Computations whose request was cancelled (503).",
           [({}, pool.cancelled_total)])
    metric("bubsub_compute_timeouts_total", "counter", "Computations stopped at their compute timeout (504).",
           [({}, pool.timeouts_total)])
    metric("bubsub_compute_reserved_bytes", "gauge", "Estimated memory reserved by running computations.",
           [({}, pool.budget.reserved if pool.budget is not None else 0)])
    metric("bubsub_ready", "gauge", "1 when the server accepts work.", [({}, int(bool(ready)))])
    return "\n".join(out) + "\n"
