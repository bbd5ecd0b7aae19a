"""FastAPI dependencies, as ``Annotated`` aliases for route signatures.

All of them are ``async def``: they never block, and FastAPI would run plain
``def`` dependencies in a thread pool (a thread hop per dependency per request).
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Path, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from bubsub.service.body import read_body
from bubsub.service.config import Settings
from bubsub.service.jobs import Job
from bubsub.service.state import ServiceState

__all__ = ["StateDep", "SettingsDep", "OwnerDep", "JobDep", "BodyDep", "JobId"]

_bearer = HTTPBearer(auto_error=False, description="Bearer token (when the server has BUBSUB_TOKENS set)")


async def get_state(request: Request) -> ServiceState:
    """The server's :class:`ServiceState`."""
    return request.app.state.service


StateDep = Annotated[ServiceState, Depends(get_state)]


async def get_settings(state: StateDep) -> Settings:
    return state.settings


SettingsDep = Annotated[Settings, Depends(get_settings)]


async def get_owner(state: StateDep, request: Request,
              _credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> str:
    """Owner id of the request (401 without a valid token when auth is on)."""
    return state.auth.owner(request.headers.get("authorization"))


OwnerDep = Annotated[str, Depends(get_owner)]

JobId = Annotated[str, Path(description="job id returned by POST /v1/jobs", max_length=128)]


async def get_job(job_id: JobId, state: StateDep, owner: OwnerDep) -> Job:
    """The job in the path, if the caller owns it (404 otherwise)."""
    return state.store.get(job_id, owner)


JobDep = Annotated[Job, Depends(get_job)]


async def get_body(request: Request, state: StateDep, _owner: OwnerDep) -> bytes:
    """The request body, bounded by ``BUBSUB_MAX_BODY_BYTES`` (read after authentication)."""
    return await read_body(request, state.settings.max_body_bytes, state.settings.body_timeout_seconds)


BodyDep = Annotated[bytes, Depends(get_body)]
