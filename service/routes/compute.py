"""``/v1/jobs/{id}/forward``, ``/vjp`` and ``/objective``: projections for posted control vertices.

A job's compute timeout bounds the work of one request: decoding and
estimating its body, the projection (its kernels stop within milliseconds of
the deadline) and the encoding of the answer; waiting for a worker does not
count. Past it the request is answered 504 (``compute_timeout``), never with
a result that came late.
"""

from __future__ import annotations

import time

from fastapi import APIRouter, Request, Response

from bubsub.core.projection.backends.base import check_deadline
from bubsub.core.projection.projector import DeadlineExceeded
from bubsub.service.budget import check_job, estimate
from bubsub.service.codec import NPY, NPZ, content_type, encode_npy, encode_npz
from bubsub.service.decoding import decode_compute_body
from bubsub.service.deps import BodyDep, JobDep, StateDep
from bubsub.service.errors import APIError
from bubsub.service.openapi import binary_body, binary_response, errors

router = APIRouter(prefix="/v1/jobs/{job_id}", tags=["compute"])

_VERTICES = "stacked control vertices of all the job's surfaces, float (n_control_total, ndim), in job order"
_ERRORS = errors(400, 401, 404, 409, 413, 415, 422, 503, 504, 507)


async def _compute(state, job, op, fn, arrays, need, spent):
    """Run ``fn(job, arrays, deadline)`` in the compute pool within its memory estimate and its job's
    compute timeout (less the ``spent`` seconds of decoding), mapping core errors to 422 and a
    computation stopped at its deadline to 504."""
    job.active += 1
    t0 = time.perf_counter()
    try:
        return await state.pool.run(op, _within, fn, job, arrays, spent, owner=job.owner, nbytes=need.total)
    except APIError:
        raise
    except DeadlineExceeded:
        state.pool.timeouts_total += 1
        raise APIError(504, f"{op} stopped after its compute timeout of {job.compute_timeout:g} s "
                            "(BUBSUB_COMPUTE_TIMEOUT_SECONDS, or the job's compute_timeout_seconds); retrying "
                            "will not help: use fewer pixels, views, surfaces, levels or less supersampling "
                            "per job", "compute_timeout") from None
    except (ValueError, TypeError, IndexError) as exc:
        raise APIError(422, f"{op}: {exc}", "invalid") from None
    except MemoryError:
        raise APIError(507, f"{op}: out of memory", "server_full") from None
    finally:
        job.active -= 1
        job.calls += 1
        job.compute_seconds += time.perf_counter() - t0
        job.touch()


def _decode(job, op, settings, body, ctype, params, allowed, required):
    """Arrays of the request with the vertices checked, the memory estimate (413 over the job's cap),
    and the seconds this took (counted against the compute timeout)."""
    t0 = time.monotonic()
    arrays = decode_compute_body(body, ctype, params, settings.max_body_bytes, allowed, required)
    arrays["vertices"] = job.check_vertices(arrays["vertices"])
    need = estimate(job, op, settings.crossings_per_ray, arrays["vertices"], arrays, len(body))
    check_job(need, settings.compute_cap)
    return arrays, need, time.monotonic() - t0


def _within(fn, job, arrays, spent):
    """``fn(job, arrays, deadline)``, the deadline taken from the moment a worker takes the call (less
    ``spent``), and checked once more after the answer is encoded: a result finished past the
    deadline is a 504, as one stopped by it."""
    deadline = job.deadline(spent)
    result = fn(job, arrays, deadline)
    check_deadline(deadline)
    return result


async def _arrays(request: Request, body: bytes, state, job, op, allowed, required):
    """The request's arrays, its estimate and the seconds they took, decoded off the event loop (cheap
    checks first)."""
    check_job(estimate(job, op, state.settings.crossings_per_ray), state.settings.compute_cap)
    ctype, params = content_type(request.headers.get("content-type"))
    return await state.decoder.run("decode", _decode, job, op, state.settings, body, ctype, params, allowed,
                                   required)


def _forward(job, arrays, deadline):
    return encode_npy(job.forward(arrays["vertices"], deadline))


def _vjp(job, arrays, deadline):
    x = arrays["vertices"]
    r = job.check_projection(arrays["residual"], "residual", deadline)
    return encode_npy(job.vjp(x, r, deadline))


def _objective(job, arrays, deadline):
    x = arrays["vertices"]
    data = arrays.get("data")
    if data is not None:
        data = job.check_projection(data, "data", deadline)
    f, g = job.objective(x, data, deadline)
    return f, encode_npz({"value": f, "gradient": g})


@router.post("/forward", response_class=Response, summary="Forward projection",
             openapi_extra=binary_body("Control vertices.", {"vertices": _VERTICES}),
             responses={**binary_response("float32 projections of the job's projection shape"), **_ERRORS})
async def forward(request: Request, job: JobDep, state: StateDep, body: BodyDep) -> Response:
    """Project the subdivided surfaces: returns float32 `.npy` of shape (angle, row, col) / (angle, col)."""
    arrays, need, spent = await _arrays(request, body, state, job, "forward", ("vertices",), ("vertices",))
    return Response(await _compute(state, job, "forward", _forward, arrays, need, spent), media_type=NPY)


@router.post("/vjp", response_class=Response, summary="Vector-Jacobian product",
             openapi_extra=binary_body("Control vertices and a residual.", {
                 "vertices": _VERTICES,
                 "residual": "float array of the projection shape",
             }, npy=False),
             responses={**binary_response("float64 gradient, shape of the vertices"), **_ERRORS})
async def vjp(request: Request, job: JobDep, state: StateDep, body: BodyDep) -> Response:
    """Gradient of `<forward(vertices), residual>` with respect to the control vertices (float64 `.npy`)."""
    arrays, need, spent = await _arrays(request, body, state, job, "vjp", ("vertices", "residual"), ("vertices", "residual"))
    return Response(await _compute(state, job, "vjp", _vjp, arrays, need, spent), media_type=NPY)


@router.post("/objective", response_class=Response, summary="Objective and gradient",
             openapi_extra=binary_body("Control vertices, optionally the data to fit.", {
                 "vertices": _VERTICES,
                 "data": "optional target projections; default: the job's data minus its background",
             }),
             responses={**binary_response("`.npz` with `value` (0-d float64, 0.5 ||forward - target||^2) and "
                                          "`gradient` (float64, shape of the vertices)", NPZ), **_ERRORS})
async def objective(request: Request, job: JobDep, state: StateDep, body: BodyDep) -> Response:
    """`f = 0.5 ||forward(vertices) - target||^2` and its gradient w.r.t. the control vertices.

    The target is the posted `data` if given, otherwise the job's data minus its background.
    The value is also in the `X-Objective` header (exact decimal repr).
    """
    arrays, need, spent = await _arrays(request, body, state, job, "objective", ("vertices", "data"), ("vertices",))
    f, payload = await _compute(state, job, "objective", _objective, arrays, need, spent)
    return Response(payload, media_type=NPZ, headers={"X-Objective": repr(float(f))})
