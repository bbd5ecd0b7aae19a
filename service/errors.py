"""JSON errors: every failure is ``{"code": ..., "detail": ...}`` with a 4xx/5xx status.

Routes raise :class:`APIError` (or one of the helpers); :func:`install` adds
handlers so that FastAPI's own errors (validation, unknown route, wrong
method) use the same body, and so that an unexpected exception still answers
JSON instead of a bare 500 page.
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

__all__ = ["APIError", "install", "error_responses", "error_response"]

log = logging.getLogger("bubsub.service")

_CODES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    406: "not_acceptable",
    408: "request_timeout",
    409: "conflict",
    411: "length_required",
    413: "too_large",
    415: "unsupported_media_type",
    422: "invalid",
    429: "too_many_requests",
    500: "internal",
    503: "busy",
    504: "timeout",
    507: "insufficient_storage",
}


class APIError(Exception):
    """An error answered as JSON.

    Parameters
    ----------
    status : int
        HTTP status.
    detail : str
        Human-readable message: what is wrong and, where useful, what to send.
    code : str, optional
        Machine-readable code (``unknown_job``, ``too_large``, ...); defaults
        to one derived from the status.
    headers : dict, optional
        Extra response headers (``Retry-After``, ``WWW-Authenticate``).
    """

    def __init__(self, status, detail, code=None, headers=None):
        super().__init__(detail)
        self.status = int(status)
        self.detail = str(detail)
        self.code = code or _CODES.get(self.status, "error")
        self.headers = dict(headers or {})

    def response(self):
        """The :class:`JSONResponse` for this error."""
        return error_response(self.status, self.detail, self.code, self.headers)


def error_response(status, detail, code=None, headers=None):
    """``{"code", "detail"}`` JSON response."""
    return JSONResponse(
        {"code": code or _CODES.get(status, "error"), "detail": detail},
        status_code=status,
        headers=headers,
    )


def error_responses(*statuses):
    """``responses=`` entries documenting JSON errors for ``statuses`` (422 always)."""
    from bubsub.service.schemas import Error

    statuses = sorted(set(statuses) | {422})  # any route with parameters can fail validation
    return {s: {"description": _CODES.get(s, "error").replace("_", " "), "model": Error} for s in statuses}


#: statuses that mean "refused by a limit, quota or timeout", counted in /metrics by error code
REFUSED = frozenset({408, 413, 429, 503, 504, 507})


def count_refusal(app, code):
    """Count a refused request in the server's metrics (if ``app`` is a bubsub server)."""
    state = getattr(getattr(app, "state", None), "service", None)
    if state is not None:
        state.requests.refuse(code)


def _retry_after(request, status, headers):
    """``headers`` with ``Retry-After`` added to a 503 that lacks one (every 503 tells when to come back)."""
    headers = dict(headers or {})
    if status == 503 and not any(k.lower() == "retry-after" for k in headers):
        state = getattr(request.app.state, "service", None)
        headers["Retry-After"] = str(state.settings.retry_after_seconds if state is not None else 1)
    return headers


async def _api_error(request: Request, exc: APIError):
    if exc.status in REFUSED:
        count_refusal(request.app, exc.code)
    return error_response(exc.status, exc.detail, exc.code, _retry_after(request, exc.status, exc.headers))


async def _http_error(request: Request, exc: StarletteHTTPException):
    detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
    return error_response(exc.status_code, detail,
                          headers=_retry_after(request, exc.status_code, getattr(exc, "headers", None)))


async def _validation_error(_request: Request, exc: RequestValidationError):
    errors = [
        {"loc": list(e.get("loc", ())), "msg": e.get("msg", ""), "type": e.get("type", "")}
        for e in exc.errors()
    ]
    text = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in errors) or "invalid request"
    return JSONResponse({"code": "invalid", "detail": text, "errors": errors}, status_code=422)


async def _unexpected(request: Request, exc: Exception):
    log.exception("unexpected error on %s %s", request.method, request.url.path)
    return error_response(500, f"internal error ({type(exc).__name__}); see the server log")


def install(app: FastAPI):
    """Register the JSON error handlers on ``app``."""
    app.add_exception_handler(APIError, _api_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(Exception, _unexpected)
