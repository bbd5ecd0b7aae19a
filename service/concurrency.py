"""Requests at once: a bound below the connection limit, so health checks always find a connection.

:class:`RequestLimitMiddleware` answers a request beyond
:attr:`~bubsub.service.server.ConnectionLimits.requests` (health checks and
metrics excepted) at once with 503, ``Retry-After`` and ``Connection:
close``, before its body is read. A request counts from its head until its
response ends, also when its client has gone (uvicorn's task still runs).
"""

from __future__ import annotations

from bubsub.service.errors import error_response

__all__ = ["RequestLimitMiddleware", "MONITORING_PATHS"]

#: paths answered whatever the load: they only report on the server
MONITORING_PATHS = frozenset({"/healthz", "/readyz", "/metrics"})


class RequestLimitMiddleware:
    """Refuse requests beyond ``limit`` at once (503 ``connections`` + ``Retry-After``).

    Parameters
    ----------
    app : ASGI application
    limit : int
        Requests at once other than :data:`MONITORING_PATHS`.
    retry_after : int
        Seconds for ``Retry-After``.
    metrics : RequestMetrics, optional
        Where refusals are counted (reason ``connections``).
    """

    def __init__(self, app, limit, retry_after=1, metrics=None):
        self.app = app
        self.limit = int(limit)
        self.retry_after = int(retry_after)
        self.metrics = metrics
        self.active = 0

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope.get("path") in MONITORING_PATHS:
            await self.app(scope, receive, send)
            return
        if self.active >= self.limit:
            if self.metrics is not None:
                self.metrics.refuse("connections")
            detail = (f"{self.active} requests are being answered, the server's limit (BUBSUB_MAX_CONNECTIONS "
                      f"less the connections kept for health checks); retry after {self.retry_after} s")
            await error_response(503, detail, "connections", {"Retry-After": str(self.retry_after),
                                                              "Connection": "close"})(scope, receive, send)
            return
        self.active += 1
        try:
            await self.app(scope, receive, send)
        finally:
            self.active -= 1
