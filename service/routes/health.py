"""``/healthz`` (the process is alive) and ``/readyz`` (it accepts work)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from bubsub.service.deps import StateDep
from bubsub.service.schemas import Status

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Status, summary="Liveness")
async def healthz() -> Status:
    """200 while the process serves HTTP at all."""
    return Status(status="ok")


@router.get("/readyz", response_model=Status, summary="Readiness",
            responses={503: {"model": Status, "description": "starting or shutting down"}})
async def readyz(state: StateDep):
    """200 when the server takes new work; 503 while starting or once shutdown has begun."""
    if not state.ready:
        retry = state.settings.retry_after_seconds
        return JSONResponse({"status": "not ready", "detail": "starting up or shutting down"}, status_code=503,
                            headers={"Retry-After": str(retry)})
    return Status(status="ready")
