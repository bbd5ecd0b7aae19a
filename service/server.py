"""The server's connection layer: descriptor-bounded connections, header and body timeouts, uvicorn's settings.

uvicorn bounds the size of a request head (h11's
``max_incomplete_event_size``) and closes idle keep-alive connections
(``timeout_keep_alive``, restarted by every byte received), but it has no
deadline for a request head or body that trickles in, and its
``limit_concurrency`` refuses health checks like any other request, with a
plain-text 503 that has no ``Retry-After``. So the protocol here
(:class:`GuardedProtocol`, an h11 protocol) does it itself:

* a connection must deliver a complete request head within
  ``BUBSUB_HEADER_TIMEOUT_SECONDS`` of connecting (or of its previous
  response), and its whole body within ``BUBSUB_BODY_TIMEOUT_SECONDS`` (plus
  a second, so that the route's own 408 goes out first), else it is closed;
* at most :attr:`ConnectionLimits.connections` connections are held, a
  number derived at start from the file-descriptor limit
  (:func:`connection_limits`), so the process never runs out of descriptors
  (asyncio's accept loop would then stop accepting for a second at a time);
* a connection beyond it takes the place of the oldest connection still
  waiting for its request head (a slow or idle client loses its slot, not
  the newcomer); only when every connection is busy with a request is the
  newcomer refused, with a 503 and ``Retry-After``. Connections that have
  not delivered a head cannot keep anyone out: a health check's head
  arrives with its connection and is answered;
* requests at once, other than ``/healthz``, ``/readyz`` and ``/metrics``,
  are bounded below the connection limit
  (:class:`~bubsub.service.concurrency.RequestLimitMiddleware`), which keeps
  :attr:`ConnectionLimits.health` connections for those.
"""

from __future__ import annotations

import json
import os
import resource
import socket
from dataclasses import dataclass

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

__all__ = ["ConnectionLimits", "connection_limits", "ConnectionGuard", "GuardedProtocol", "protocol_class",
           "uvicorn_config", "Server", "MAX_HEADER_BYTES", "FD_RESERVE", "BODY_GRACE_SECONDS", "LISTEN_QUEUE"]

#: largest request head (request line and headers); h11 answers 400 beyond it
MAX_HEADER_BYTES = 16 * 1024
#: file descriptors kept for the process itself (files, pipes, compiled-kernel caches) besides those open at start
FD_RESERVE = 64
#: a body still arriving this long after BUBSUB_BODY_TIMEOUT_SECONDS closes its connection (the route answers
#: 408 at the timeout itself; this covers bodies no route reads)
BODY_GRACE_SECONDS = 1.0
#: a refused connection is closed this long after its 503 was sent, so the client can read it
REFUSE_LINGER_SECONDS = 0.5
#: connections the kernel queues for :class:`Server` before they are accepted (they hold no descriptor there)
LISTEN_QUEUE = 1024


@dataclass(frozen=True)
class ConnectionLimits:
    """Connection limits of one server, fixed at start.

    Attributes
    ----------
    connections : int
        Connections held at once (``BUBSUB_MAX_CONNECTIONS``, lowered to fit the descriptors).
    health : int
        Connections beyond ``requests`` kept for ``/healthz``, ``/readyz`` and ``/metrics``, and extra
        connections briefly allowed when every held one is busy.
    requests : int
        Requests at once other than health checks and metrics (``connections - health``).
    backlog : int
        Pending connections the kernel queues (``BUBSUB_BACKLOG``, lowered likewise): asyncio accepts up
        to this many in one go, before any is looked at.
    nofile : int or None
        The soft descriptor limit they were derived from (None: unlimited).
    """

    connections: int
    health: int
    requests: int
    backlog: int
    nofile: int | None


def _open_descriptors():
    """File descriptors this process has open (0 where it cannot be counted)."""
    try:
        return len(os.listdir("/proc/self/fd")) - 1  # less the one listing the directory
    except OSError:
        return 0


def connection_limits(settings, nofile=None):
    """:class:`ConnectionLimits` for ``settings`` under the descriptor limit ``nofile``.

    Parameters
    ----------
    settings : Settings
    nofile : int, optional
        Soft ``RLIMIT_NOFILE`` (default: this process's).

    Notes
    -----
    Besides the held connections, descriptors go to those already open, to
    :data:`FD_RESERVE`, and to connections accepted but not yet looked at:
    asyncio accepts up to ``backlog`` per turn of the event loop and a
    connection is closed a few turns later, so four backlogs are kept. The
    backlog is at most a third of the connections, so that one turn's
    newcomers cannot push a connection out before its request head is read.
    """
    if nofile is None:
        nofile = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    wanted = settings.max_connections
    if nofile == resource.RLIM_INFINITY:
        nofile, free = None, None
        connections = wanted
    else:
        free = nofile - _open_descriptors() - FD_RESERVE
        # connections + health (<= connections / 8) + 4 backlogs (<= connections / 3): at most 2.5 x connections
        connections = max(2, min(wanted, int(free / 2.5)))
    health = max(1, min(32, connections // 8))
    backlog = max(1, min(settings.backlog, connections // 3))
    if free is not None:
        backlog = max(1, min(backlog, (free - connections - health) // 4))
    return ConnectionLimits(connections, health, max(1, connections - health), backlog, nofile)


class ConnectionGuard:
    """What the connections of one server share: limits, timeouts, and who waits for a request head.

    Parameters
    ----------
    limits : ConnectionLimits
    header_timeout, body_timeout : float
        Seconds (``BUBSUB_HEADER_TIMEOUT_SECONDS``, ``BUBSUB_BODY_TIMEOUT_SECONDS``).
    retry_after : int
        ``Retry-After`` of a refusal.
    metrics : RequestMetrics, optional
        Where closed connections are counted (``header_timeout``, ``body_timeout``, ``evicted``,
        ``connections``).
    """

    def __init__(self, limits, header_timeout, body_timeout, retry_after=1, metrics=None):
        self.limits = limits
        self.header_timeout = float(header_timeout)
        self.body_timeout = float(body_timeout)
        self.retry_after = int(retry_after)
        self.metrics = metrics
        self.waiting = {}  # protocol -> None: connections waiting for a request head, oldest first
        self.refusing = 0  # refused connections still sending their 503

    def count(self, reason):
        if self.metrics is not None:
            self.metrics.refuse(reason)

    def refusal(self, open_connections):
        """The bytes of a 503 for a connection refused at the limit."""
        body = json.dumps({"code": "connections", "detail": (
            f"{open_connections} connections are open, over the server's limit of {self.limits.connections} "
            f"(BUBSUB_MAX_CONNECTIONS, lowered to fit {self.limits.nofile} file descriptors) and every one is "
            f"busy with a request; retry after {self.retry_after} s")}).encode()
        head = (f"HTTP/1.1 503 Service Unavailable\r\ncontent-type: application/json\r\n"
                f"content-length: {len(body)}\r\nretry-after: {self.retry_after}\r\nconnection: close\r\n\r\n")
        return head.encode("ascii") + body

    def make_room(self, newcomer):
        """Close the oldest connection other than ``newcomer`` that waits for a request head; False if none."""
        for victim in self.waiting:
            if victim is not newcomer:
                self.waiting.pop(victim)
                self.count("evicted")
                victim.transport.close()
                return True
        return False


class GuardedProtocol(H11Protocol):
    """uvicorn's h11 protocol with the header and body deadlines and the connection limit of :attr:`guard`.

    ``guard`` (a :class:`ConnectionGuard`) is a class attribute, set by :func:`protocol_class`.
    """

    guard: ConnectionGuard = None

    def connection_made(self, transport):
        super().connection_made(transport)
        self._head_timer = self._body_timer = None
        self._refused = self._lingering = False
        guard, limits = self.guard, self.guard.limits
        n = len(self.connections)
        if n > limits.connections and not guard.make_room(self) and n > limits.connections + limits.health:
            self._refuse(n)
            return
        self._wait_for_head()

    # -- states ------------------------------------------------------------------------
    def _refuse(self, n):
        self._refused = True
        self.guard.count("connections")
        if self.guard.refusing >= self.guard.limits.health:
            self.transport.close()  # a flood of refusals: no lingering
            return
        self._lingering = True
        self.guard.refusing += 1
        self.transport.write(self.guard.refusal(n))
        if self.transport.can_write_eof():
            self.transport.write_eof()
        # closed a little later: closing with the client's request unread would reset the connection
        # before the client has read the 503
        self._head_timer = self.loop.call_later(REFUSE_LINGER_SECONDS, self.transport.close)

    def _wait_for_head(self):
        """From connecting, or from the end of a response: a request head must come within the header timeout."""
        self._cancel_timers()
        self.guard.waiting[self] = None
        self._head_timer = self.loop.call_later(self.guard.header_timeout, self._head_timeout)

    def _head_arrived(self):
        self.guard.waiting.pop(self, None)
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _cancel_timers(self):
        for name in ("_head_timer", "_body_timer"):
            timer = getattr(self, name, None)
            if timer is not None:
                timer.cancel()
                setattr(self, name, None)

    def _head_timeout(self):
        self._head_timer = None
        # IDLE: h11 has not seen a complete request head since the connection (or last response) began
        if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
            self.guard.waiting.pop(self, None)
            self.guard.count("header_timeout")
            self.transport.close()

    def _body_timeout(self):
        self._body_timer = None
        if self.conn.their_state is h11.SEND_BODY and not self.transport.is_closing():
            self.guard.count("body_timeout")
            self.transport.close()

    # -- uvicorn's hooks -----------------------------------------------------------------
    def data_received(self, data):
        if self._refused:
            return  # read and dropped, so that closing later sends no reset
        super().data_received(data)

    def handle_events(self):
        super().handle_events()
        state = self.conn.their_state
        if state is h11.IDLE or self.transport.is_closing():
            return
        self._head_arrived()
        if state is h11.SEND_BODY:
            if self._body_timer is None:
                self._body_timer = self.loop.call_later(self.guard.body_timeout + BODY_GRACE_SECONDS,
                                                        self._body_timeout)
        elif self._body_timer is not None:  # the body is complete
            self._body_timer.cancel()
            self._body_timer = None

    def on_response_complete(self):
        super().on_response_complete()
        if not self.transport.is_closing() and self.conn.their_state is h11.IDLE:
            self._wait_for_head()  # the next request on this keep-alive connection

    def connection_lost(self, exc):
        self._cancel_timers()
        self.guard.waiting.pop(self, None)
        if self._lingering:
            self._lingering = False
            self.guard.refusing -= 1
        super().connection_lost(exc)


def protocol_class(guard):
    """A :class:`GuardedProtocol` subclass bound to ``guard`` (uvicorn takes a class)."""
    return type("BubsubH11Protocol", (GuardedProtocol,), {"guard": guard})


def uvicorn_config(app, settings, **overrides):
    """The :class:`uvicorn.Config` that serves ``app`` with ``settings``' limits.

    Parameters
    ----------
    app : fastapi.FastAPI
        From :func:`~bubsub.service.app.create_app` (its state holds the :class:`ConnectionLimits`
        its request limit was made with, and the metrics that count closed connections).
    settings : Settings
    **overrides
        Further ``uvicorn.Config`` arguments (``log_level``, ``host`` ...).
    """
    state = getattr(app.state, "service", None)
    limits = getattr(state, "limits", None) or connection_limits(settings)
    guard = ConnectionGuard(limits, settings.header_timeout_seconds, settings.body_timeout_seconds,
                            settings.retry_after_seconds, state.requests if state is not None else None)
    kwargs = dict(
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        timeout_graceful_shutdown=settings.shutdown_timeout_seconds,
        proxy_headers=True,
        server_header=False,
        http=protocol_class(guard),
        limit_concurrency=None,  # the guard and RequestLimitMiddleware bound connections and requests
        backlog=limits.backlog,
        timeout_keep_alive=settings.keepalive_timeout_seconds,
        h11_max_incomplete_event_size=MAX_HEADER_BYTES,
    )
    kwargs.update(overrides)
    return uvicorn.Config(app, **kwargs)



class Server(uvicorn.Server):
    """uvicorn's server, its listening sockets queueing up to :data:`LISTEN_QUEUE` connections.

    asyncio takes one number for the kernel's queue and for the connections
    it accepts in one go; the second is kept small to bound descriptors
    (:func:`connection_limits`), and with it alone a burst of connections
    would overflow the kernel's queue, whose dropped connection attempts are
    retried only a second later (a health check would miss its second).
    """

    async def startup(self, sockets=None):
        await super().startup(sockets=sockets)
        for server in getattr(self, "servers", ()):
            for listener in server.sockets or ():
                sock = socket.socket(fileno=listener.fileno())  # the same descriptor, not a copy
                try:
                    sock.listen(max(LISTEN_QUEUE, self.config.backlog))
                finally:
                    sock.detach()
