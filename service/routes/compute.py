"""``/v1/jobs/{id}/forward``, ``/vjp`` and ``/objective``: projections for posted control vertices."""

from __future__ import annotations

import time

from fastapi import APIRouter, Request, Response

from ..codec import NPY, NPZ, content_type, decode_arrays, encode_npy, encode_npz
from ..deps import BodyDep, JobDep, StateDep
from ..errors import APIError
from ..openapi import binary_body, binary_response, errors

router = APIRouter(prefix="/v1/jobs/{job_id}", tags=["compute"])

_VERTICES = "stacked control vertices of all the job's surfaces, float (n_control_total, ndim), in job order"
_ERRORS = errors(400, 401, 404, 409, 413, 415, 422, 503, 507)


async def _compute(state, job, op, fn, *args):
    """Run ``fn`` in the compute pool for ``job``, mapping core errors to 422."""
    job.active += 1
    t0 = time.perf_counter()
    try:
        return await state.pool.run(op, fn, *args)
    except APIError:
        raise
    except (ValueError, TypeError, IndexError) as exc:
        raise APIError(422, f"{op}: {exc}", "invalid") from None
    except MemoryError:
        raise APIError(507, f"{op}: out of memory", "server_full") from None
    finally:
        job.active -= 1
        job.calls += 1
        job.compute_seconds += time.perf_counter() - t0
        job.touch()


def _arrays(request: Request, body: bytes, state, allowed, required):
    ctype, params = content_type(request.headers.get("content-type"))
    arrays = decode_arrays(body, ctype, params, state.settings.max_body_bytes, allowed)
    missing = [k for k in required if k not in arrays]
    if missing:
        raise APIError(422, f"missing arrays {missing}; send {NPZ} or multipart with {list(allowed)}",
                       "missing_array")
    return arrays


def _forward(job, arrays):
    return encode_npy(job.forward(job.check_vertices(arrays["vertices"])))


def _vjp(job, arrays):
    x = job.check_vertices(arrays["vertices"])
    r = job.check_projection(arrays["residual"], "residual")
    return encode_npy(job.vjp(x, r))


def _objective(job, arrays):
    x = job.check_vertices(arrays["vertices"])
    data = arrays.get("data")
    if data is not None:
        data = job.check_projection(data, "data")
    f, g = job.objective(x, data)
    return f, encode_npz({"value": f, "gradient": g})


@router.post("/forward", response_class=Response, summary="Forward projection",
             openapi_extra=binary_body("Control vertices.", {"vertices": _VERTICES}),
             responses={**binary_response("float32 projections of the job's projection shape"), **_ERRORS})
async def forward(request: Request, job: JobDep, state: StateDep, body: BodyDep) -> Response:
    """Project the subdivided surfaces: returns float32 `.npy` of shape (angle, row, col) / (angle, col)."""
    arrays = _arrays(request, body, state, ("vertices",), ("vertices",))
    return Response(await _compute(state, job, "forward", _forward, job, arrays), media_type=NPY)


@router.post("/vjp", response_class=Response, summary="Vector-Jacobian product",
             openapi_extra=binary_body("Control vertices and a residual.", {
                 "vertices": _VERTICES,
                 "residual": "float array of the projection shape",
             }, npy=False),
             responses={**binary_response("float64 gradient, shape of the vertices"), **_ERRORS})
async def vjp(request: Request, job: JobDep, state: StateDep, body: BodyDep) -> Response:
    """Gradient of `<forward(vertices), residual>` with respect to the control vertices (float64 `.npy`)."""
    arrays = _arrays(request, body, state, ("vertices", "residual"), ("vertices", "residual"))
    return Response(await _compute(state, job, "vjp", _vjp, job, arrays), media_type=NPY)


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
    arrays = _arrays(request, body, state, ("vertices", "data"), ("vertices",))
    f, payload = await _compute(state, job, "objective", _objective, job, arrays)
    return Response(payload, media_type=NPZ, headers={"X-Objective": repr(float(f))})
