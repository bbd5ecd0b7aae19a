"""``/v1/jobs``: create, list, inspect and delete jobs."""

from __future__ import annotations

import time

from fastapi import APIRouter, Request, Response

from bubsub.service.budget import check_job, estimate
from bubsub.service.codec import JSON, content_type
from bubsub.service.decoding import check_json_size, decode_job_body
from bubsub.service.deps import BodyDep, JobDep, OwnerDep, StateDep
from bubsub.service.jobs import Job, build_job, topology_bytes
from bubsub.service.openapi import errors, job_create_body
from bubsub.service.schemas import JobCreate, JobInfo, JobList, SurfaceGroupInfo

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])


def job_info(job: Job, ttl: float) -> JobInfo:
    """The public description of ``job``."""
    idle = time.monotonic() - job.last_used
    groups = []
    for g in job.groups:
        n_fine = g.template.S.shape[0] if g.template is not None else None
        groups.append(SurfaceGroupInfo(n_control=g.n_control, n_faces=None if g.faces is None else len(g.faces),
                                       levels=g.levels, attenuation=g.attenuation, count=g.count, n_fine=n_fine))
    return JobInfo(
        id=job.id, kind=job.geometry.kind, ndim=job.ndim, n_angles=job.geometry.n_angles,
        projection_shape=list(job.geometry.shape), vertices_shape=list(job.vertices_shape),
        supersampling=job.supersampling, surfaces=groups, n_surfaces=job.n_surfaces,
        has_data=job.data is not None, has_background=job.background is not None,
        memory_bytes=job.nbytes(), created=job.created, idle_seconds=idle,
        expires_in_seconds=max(0.0, ttl - idle), calls=job.calls, compute_seconds=job.compute_seconds,
        compute_timeout_seconds=job.compute_timeout,
    )


def _estimate(spec: JobCreate, arrays: dict) -> int:
    """Bytes a job will hold, estimated before building it (to refuse it early)."""
    n = len(spec.geometry.vectors) * 12 * 8
    for s in spec.surfaces:
        n_faces = None if s.faces is None else len(s.faces)
        n += (n_faces or 0) * 24 + topology_bytes(s.n_control, n_faces, s.levels)
    sizes = [a.size * 4 for k, a in arrays.items() if k in ("data", "background")]
    return n + sum(sizes) + (min(sizes) if len(sizes) == 2 else 0)


@router.post(
    "",
    status_code=201,
    response_model=JobInfo,
    summary="Create a job",
    openapi_extra=job_create_body(),
    responses=errors(400, 401, 413, 415, 422, 503, 507),
)
async def create_job(request: Request, response: Response, state: StateDep, owner: OwnerDep,
                     body: BodyDep) -> JobInfo:
    """Create a job from a scan geometry and the topology of the surfaces to fit.

    The server subdivides the surfaces itself; compute requests then send only
    the stacked control vertices. The `Location` header names the new job.
    """
    settings = state.settings
    ctype, params = content_type(request.headers.get("content-type"))
    if ctype == JSON:
        check_json_size(body, settings.max_json_bytes)  # before a thread is taken for it
    spec, arrays = await state.decoder.run("decode", decode_job_body, body, ctype, params, settings.max_json_bytes)
    state.store.admit(_estimate(spec, arrays), owner=owner)
    job_id = state.store.new_id()
    job = await state.pool.run("create", build_job, job_id, owner, spec, settings,
                               arrays.get("vertices"), arrays.get("data"), arrays.get("background"), owner=owner)
    # a job none of whose computations would fit is refused now, not on its first request
    check_job(estimate(job, "forward", settings.crossings_per_ray), settings.compute_cap)
    state.store.add(job)
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    return job_info(job, state.store.ttl)


@router.get("", response_model=JobList, summary="List your jobs", responses=errors(401))
async def list_jobs(state: StateDep, owner: OwnerDep) -> JobList:
    """Jobs created with the caller's token (all jobs when authentication is off)."""
    state.store.expire()
    return JobList(jobs=[job_info(j, state.store.ttl) for j in state.store.owned(owner)])


@router.get("/{job_id}", response_model=JobInfo, summary="Inspect a job", responses=errors(401, 404))
async def get_job(job: JobDep, state: StateDep) -> JobInfo:
    """What the job holds: geometry, surfaces, data, memory, idle time."""
    return job_info(job, state.store.ttl)


@router.delete("/{job_id}", status_code=204, summary="Delete a job", responses=errors(401, 404))
async def delete_job(job: JobDep, state: StateDep, owner: OwnerDep) -> Response:
    """Delete the job and free its memory."""
    state.store.delete(job.id, owner)
    return Response(status_code=204)
