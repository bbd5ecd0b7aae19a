"""``/metrics``: Prometheus text format."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import PlainTextResponse

from bubsub.service.deps import StateDep
from bubsub.service.metrics import CONTENT_TYPE, render

router = APIRouter(tags=["metrics"])


@router.get("/metrics", response_class=PlainTextResponse, summary="Prometheus metrics",
            responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}}})
async def metrics(state: StateDep) -> PlainTextResponse:
    """Requests, jobs, memory held and compute time, in the Prometheus text exposition format."""
    text = render(state.requests, state.store, state.pool, state.ready, state.settings)
    return PlainTextResponse(text, media_type=CONTENT_TYPE)
