"""uvicorn settings of the server: connection limits and timeouts against slow clients.

uvicorn bounds requests at once (``limit_concurrency``: 503 beyond it), idle
keep-alive connections (``timeout_keep_alive``) and the size of a request
head (h11's ``max_incomplete_event_size``), but it waits forever for the head
of a request that trickles in. :class:`HeaderTimeoutProtocol` closes a
connection that has not sent a complete request head within
``BUBSUB_HEADER_TIMEOUT_SECONDS`` of connecting (or of its previous
response), and closes at once a connection beyond ``max_connections``, so
that the process never runs out of file descriptors (at that point asyncio's
accept loop retries in a busy loop and no timer, not even these, runs). The
body has its own deadline (``read_body``).
"""

from __future__ import annotations

import resource

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

__all__ = ["HeaderTimeoutProtocol", "protocol_class", "connection_limit", "uvicorn_config", "MAX_HEADER_BYTES",
           "FD_RESERVE"]

#: largest request head (request line and headers); h11 answers 400 beyond it
MAX_HEADER_BYTES = 16 * 1024
#: file descriptors kept for the process itself (not connections)
FD_RESERVE = 64


class HeaderTimeoutProtocol(H11Protocol):
    """h11 protocol that drops connections whose request head is not complete in time.

    ``header_timeout`` (seconds), ``max_connections`` and ``metrics`` (a
    :class:`RequestMetrics` or None) are class attributes, set by
    :func:`protocol_class`.
    """

    header_timeout = 10.0
    max_connections = None
    metrics = None

    def connection_made(self, transport):
        super().connection_made(transport)
        self._head_timer = None
        if self.max_connections is not None and len(self.connections) > self.max_connections:
            if self.metrics is not None:
                self.metrics.refuse("connections")
            transport.close()
            return
        self._arm_head_timer()

    def _arm_head_timer(self):
        self._cancel_head_timer()
        self._head_timer = self.loop.call_later(self.header_timeout, self._head_timeout)

    def _cancel_head_timer(self):
        if getattr(self, "_head_timer", None) is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_timeout(self):
        self._head_timer = None
        # IDLE: h11 has not seen a complete request head since the connection (or last response) began
        if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
            if self.metrics is not None:
                self.metrics.refuse("header_timeout")
            self.transport.close()

    def handle_events(self):
        super().handle_events()
        if self.conn.their_state is not h11.IDLE:
            self._cancel_head_timer()  # a request head arrived: the body has its own deadline

    def on_response_complete(self):
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm_head_timer()  # the next request on this keep-alive connection

    def connection_lost(self, exc):
        self._cancel_head_timer()
        super().connection_lost(exc)


def protocol_class(header_timeout, max_connections=None, metrics=None):
    """A :class:`HeaderTimeoutProtocol` subclass with these settings (uvicorn takes a class)."""
    return type("BubsubH11Protocol", (HeaderTimeoutProtocol,),
                {"header_timeout": float(header_timeout), "max_connections": max_connections, "metrics": metrics})


def connection_limit(settings):
    """``max_connections``, lowered to fit the process's file-descriptor limit.

    Up to ``backlog`` connections are accepted in one go before any is
    looked at, and the process needs descriptors of its own (files, pipes,
    the listening socket): those are kept free.
    """
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY:
        return settings.max_connections
    return max(1, min(settings.max_connections, soft - settings.backlog - FD_RESERVE))


def uvicorn_config(app, settings, **overrides):
    """The :class:`uvicorn.Config` that serves ``app`` with ``settings``' limits.

    Parameters
    ----------
    app : fastapi.FastAPI
        From :func:`~bubsub.service.app.create_app` (its metrics count header timeouts).
    settings : Settings
    **overrides
        Further ``uvicorn.Config`` arguments (``log_level``, ``host`` ...).
    """
    state = getattr(app.state, "service", None)
    limit = connection_limit(settings)
    kwargs = dict(
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        timeout_graceful_shutdown=settings.shutdown_timeout_seconds,
        proxy_headers=True,
        server_header=False,
        http=protocol_class(settings.header_timeout_seconds, limit, state.requests if state is not None else None),
        limit_concurrency=limit,
        backlog=settings.backlog,
        timeout_keep_alive=settings.keepalive_timeout_seconds,
        h11_max_incomplete_event_size=MAX_HEADER_BYTES,
    )
    kwargs.update(overrides)
    return uvicorn.Config(app, **kwargs)
