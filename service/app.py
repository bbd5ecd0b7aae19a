"""The FastAPI application: ``uvicorn bubsub.service.app:app``.

:func:`create_app` builds an application from a :class:`Settings` object; the
module attribute ``app`` is one built from the environment on first access. Its lifespan starts
the idle-job sweeper, marks the server ready, and on shutdown marks it not
ready first, lets in-flight computations finish, and frees the jobs.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import threading

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from bubsub.service import errors
from bubsub.service.body import BodyLimitMiddleware
from bubsub.service.concurrency import RequestLimitMiddleware
from bubsub.service.config import Settings, get_settings
from bubsub.service.metrics import MetricsMiddleware
from bubsub.service.openapi import EXTRA_MODELS, add_docs
from bubsub.service.routes import ROUTERS
from bubsub.service.schemas import DataFile
from bubsub.service.server import connection_limits
from bubsub.service.state import ServiceState
from bubsub.core import MeshProjector, ScanGeometry, sphere_surface

__all__ = ["create_app", "app"]

log = logging.getLogger("bubsub.service")

VERSION = "1"

DESCRIPTION = """\
Projection server of **bubsub**: forward projection, vector-Jacobian product and
objective of subdivision-surface bubble meshes, for fits that run on the client.

* A **job** holds a scan geometry, the topology of the surfaces being fitted and,
  optionally, the measured data and the stationary background.
* Compute requests send only the stacked **control vertices** (`.npy`,
  `application/x-npy`); several arrays travel as `.npz` (`application/x-npz`) or
  `multipart/form-data` with `.npy` parts. Responses are `.npy`/`.npz`.
* Errors are JSON `{"code": ..., "detail": ...}`; a full queue answers 503 with
  `Retry-After`.
"""


async def _sweep(state: ServiceState):
    """Expire idle jobs every ``sweep_interval`` seconds."""
    while True:
        await asyncio.sleep(state.settings.sweep_interval)
        n = state.store.expire()
        if n:
            log.info("expired %d idle job(s)", n)


def _ray_casting_backend():
    """Project a tiny sphere once, so the first request does not compile the kernel."""
    projector = MeshProjector(ScanGeometry.parallel([0.0], pixel_size=1.0, cols=2, rows=2))
    projector.forward([sphere_surface([0.0, 0.0, 0.0], 1.0, 0.1)])
    return projector.backend


def _limit_blas(threads):
    """Limit the process's BLAS thread pools; returns an object to restore them, or None."""
    if not threads:
        return None
    try:
        import scipy.linalg  # noqa: F401 - load scipy's own BLAS too, so that it is limited as well
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl is in the service extra
        log.warning("threadpoolctl is not installed; BUBSUB_BLAS_THREADS is ignored")
        return None
    return threadpool_limits(limits=int(threads), user_api="blas")


def _chain_signals(state: ServiceState, loop):
    """Make SIGTERM/SIGINT turn readiness off before the server's own handler runs.

    With ``shutdown_grace_seconds`` > 0 the server keeps serving (not ready)
    for that long, so load balancers stop sending work before it drains.
    Returns the handlers to restore, or ``{}`` outside the main thread.
    """
    if threading.current_thread() is not threading.main_thread():
        return {}
    grace = state.settings.shutdown_grace_seconds
    previous = {}

    def handler(sig, frame):
        first = state.ready
        state.ready = False
        prev = previous.get(sig)
        if not callable(prev):
            prev = signal.default_int_handler if sig == signal.SIGINT else None
        if prev is None:
            return
        if first and grace > 0:
            log.info("signal %d: not ready; draining starts in %.1f s", sig, grace)
            loop.call_soon_threadsafe(loop.call_later, grace, prev, sig, frame)
        else:
            prev(sig, frame)

    for sig in (signal.SIGTERM, signal.SIGINT):
        try:
            previous[sig] = signal.signal(sig, handler)
        except (ValueError, OSError):  # pragma: no cover - not the main thread / unsupported
            pass
    return previous


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the projection server.

    Parameters
    ----------
    settings : Settings, optional
        Defaults to the environment (``BUBSUB_*`` variables).

    Returns
    -------
    fastapi.FastAPI
        ``app.state.service`` is the :class:`ServiceState`.
    """
    settings = settings or get_settings()
    state = ServiceState.from_settings(settings)
    state.limits = connection_limits(settings)  # from the descriptor limit at start; uvicorn_config uses them too

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        loop = asyncio.get_running_loop()
        blas = _limit_blas(state.settings.blas_threads)
        sweeper = asyncio.create_task(_sweep(state), name="bubsub-sweeper")
        previous = _chain_signals(state, loop)
        # load (or compile) the ray-casting kernel before declaring readiness
        backend = await loop.run_in_executor(None, _ray_casting_backend)
        state.ready = True
        log.info("bubsub projection server ready (%d compute workers, queue %d, auth %s, %s ray casting)",
                 state.pool.workers, state.pool.max_queue, "on" if state.auth.enabled else "off", backend)
        try:
            yield
        finally:
            state.ready = False
            sweeper.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sweeper
            # uvicorn has waited for in-flight requests; finish any computation left
            # (blocking is fine here: nothing else is served any more).
            state.pool.shutdown(wait=True)
            state.decoder.shutdown(wait=True)
            state.store.clear()
            if blas is not None:
                blas.restore_original_limits()
            for sig, prev in previous.items():
                with contextlib.suppress(ValueError, OSError, TypeError):
                    signal.signal(sig, prev)

    app = FastAPI(
        title="bubsub projection server",
        version=VERSION,
        description=DESCRIPTION,
        lifespan=lifespan,
        docs_url=None,  # add_docs: the same page with its script and style sheet served here, not from a CDN
        redoc_url=None,
    )
    app.state.service = state
    errors.install(app)
    for router in ROUTERS:
        app.include_router(router)
    add_docs(app)
    app.add_middleware(BodyLimitMiddleware, limit=settings.max_body_bytes, metrics=state.requests)
    app.add_middleware(RequestLimitMiddleware, limit=state.limits.requests, retry_after=settings.retry_after_seconds,
                       metrics=state.requests)
    app.add_middleware(MetricsMiddleware, metrics=state.requests)
    app.openapi = lambda: _openapi(app)
    return app


def _openapi(app: FastAPI):
    """OpenAPI schema, with the models only used in hand-written request bodies."""
    if app.openapi_schema:
        return app.openapi_schema
    schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    for model in (*EXTRA_MODELS, DataFile):
        js = model.model_json_schema(ref_template="#/components/schemas/{model}")
        for name, sub in js.pop("$defs", {}).items():
            components.setdefault(name, sub)
        components.setdefault(model.__name__, js)
    app.openapi_schema = schema
    return schema


def __getattr__(name):
    """``app`` is built on first access (``uvicorn bubsub.service.app:app``), not on import."""
    if name == "app":
        value = globals()["app"] = create_app()
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
