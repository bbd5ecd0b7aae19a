"""Bounded request bodies.

:class:`BodyLimitMiddleware` refuses, before the application sees the request,
any body whose ``Content-Length`` is over the limit. :func:`read_body` reads a
body in the route, counting the bytes as they stream in, so a chunked body (no
``Content-Length``) is cut off with 413 as soon as it passes the limit, and a
body that trickles in is cut off with 408 at a deadline.
"""

from __future__ import annotations

import asyncio

from starlette.requests import ClientDisconnect, Request

from bubsub.service.errors import APIError, error_response

__all__ = ["BodyLimitMiddleware", "read_body"]


def _too_large(limit, size=None):
    what = f"{size} bytes" if size is not None else "more bytes"
    return APIError(413, f"request body of {what} is over the {limit}-byte limit (BUBSUB_MAX_BODY_BYTES)",
                    "too_large", {"Connection": "close"})


class BodyLimitMiddleware:
    """Answer 413 to requests whose ``Content-Length`` exceeds ``limit``.

    Parameters
    ----------
    app : ASGI application
    limit : int
        Largest body in bytes.
    metrics : RequestMetrics, optional
        Where refusals are counted.
    """

    def __init__(self, app, limit, metrics=None):
        self.app = app
        self.limit = int(limit)
        self.metrics = metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] == "http":
            for key, value in scope.get("headers", ()):
                if key == b"content-length":
                    try:
                        size = int(value)
                    except ValueError:
                        await error_response(400, "Content-Length is not an integer")(scope, receive, send)
                        return
                    if size > self.limit:
                        if self.metrics is not None:
                            self.metrics.refuse("too_large")
                        await _too_large(self.limit, size).response()(scope, receive, send)
                        return
        await self.app(scope, receive, send)


async def read_body(request: Request, limit: int, timeout: float | None = None) -> bytes:
    """The whole body of ``request``, refusing it with 413 past ``limit`` bytes.

    Parameters
    ----------
    request : starlette.requests.Request
    limit : int
    timeout : float, optional
        Seconds the whole body may take to arrive (``BUBSUB_BODY_TIMEOUT_SECONDS``).

    Returns
    -------
    bytes

    Raises
    ------
    APIError
        413 when the declared or streamed size exceeds ``limit``; 400 when
        the client disconnects before the body is complete; 408 when it is
        not complete within ``timeout``.
    """
    declared = request.headers.get("content-length")
    if declared is not None:
        try:
            if int(declared) > limit:
                raise _too_large(limit, int(declared))
        except ValueError:
            raise APIError(400, "Content-Length is not an integer") from None
    chunks = []
    size = 0
    try:
        async with asyncio.timeout(timeout):
            async for chunk in request.stream():
                size += len(chunk)
                if size > limit:
                    raise _too_large(limit)
                chunks.append(chunk)
    except ClientDisconnect:
        raise APIError(400, "client disconnected before the body was complete", "truncated") from None
    except TimeoutError:
        raise APIError(408, f"request body not complete after {timeout} s ({size} bytes arrived; "
                            f"BUBSUB_BODY_TIMEOUT_SECONDS)", "body_timeout", {"Connection": "close"}) from None
    return b"".join(chunks)
