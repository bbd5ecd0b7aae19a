"""``/v1/jobs/{id}/data`` and ``/background``: the measured projections a job fits."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, Request

from bubsub.service.codec import JSON, NPY, content_type, decode_npy, decode_npz
from bubsub.service.decoding import decode_upload_body
from bubsub.service.deps import BodyDep, JobDep, StateDep
from bubsub.service.errors import APIError
from bubsub.service.openapi import errors
from bubsub.service.schemas import DataFile, JobInfo
from bubsub.service.routes.jobs import job_info

router = APIRouter(prefix="/v1/jobs/{job_id}", tags=["data"])

_BINARY = {"type": "string", "format": "binary"}


def _upload_body(what):
    return {
        "requestBody": {
            "required": True,
            "description": (
                f"The {what} as a float32/float64 `.npy` array of the job's projection shape "
                "(angle, row, col) or (angle, col); or JSON `{\"file\": ..., \"key\": ...}` naming a `.npy`/"
                "`.npz` file in the server's scan directory (BUBSUB_SCAN_DIR)."
            ),
            "content": {
                NPY: {"schema": _BINARY},
                JSON: {"schema": {"$ref": "#/components/schemas/DataFile"}},
            },
        }
    }


def _resolve(settings, spec: DataFile) -> Path:
    """The file ``spec`` names inside the scan directory (422 for anything else, never a 500)."""
    if settings.scan_dir is None:
        raise APIError(422, "this server has no scan directory (BUBSUB_SCAN_DIR); upload the array as "
                            f"{NPY} instead", "no_scan_dir")
    try:
        root = Path(settings.scan_dir).resolve()
        path = (root / spec.file).resolve()
        inside = path.is_relative_to(root)
        is_file = inside and path.is_file()
    except (ValueError, OSError, RuntimeError) as exc:
        # NUL bytes (ValueError), names over NAME_MAX (OSError), symlink loops (RuntimeError/OSError)
        raise APIError(422, f"file {spec.file!r} cannot be used: {exc}", "bad_path") from None
    if not inside:
        raise APIError(422, f"file {spec.file!r} is outside the scan directory", "bad_path")
    if not is_file:
        raise APIError(422, f"file {spec.file!r} not found in the scan directory", "bad_path")
    return path


def _read_file(settings, spec: DataFile, limit: int):
    path = _resolve(settings, spec)
    size = path.stat().st_size
    if size > limit:
        raise APIError(413, f"file {spec.file!r} has {size} bytes, over the per-job cap of {limit}", "job_too_large")
    raw = path.read_bytes()
    if raw[:2] == b"PK":
        arrays = decode_npz(raw, limit, spec.file)
        if spec.key is None and len(arrays) == 1:
            return next(iter(arrays.values()))
        if spec.key not in arrays:
            raise APIError(422, f"{spec.file!r} holds arrays {sorted(arrays)}; name one with 'key'", "bad_key")
        return arrays[spec.key]
    return decode_npy(raw, spec.file)


def _checked(job, which, raw):
    """The upload as float32 and the job's arrays with it (run in the pool: it touches the whole array)."""
    arr = job.check_projection(raw, which)
    return arr, job.arrays_with(**{which: arr})


async def _put(which: str, request: Request, body: bytes, job, state) -> JobInfo:
    settings = state.settings
    ctype, _ = content_type(request.headers.get("content-type"))
    raw = await state.decoder.run("decode", decode_upload_body, body, ctype, which, settings.max_json_bytes)
    if isinstance(raw, DataFile):
        raw = await state.pool.run("load", _read_file, settings, raw, settings.job_max_bytes, owner=job.owner)
    arr, (data, background, target) = await state.pool.run("upload", _checked, job, which, raw, owner=job.owner)
    state.store.admit(job.nbytes(**{which: arr}), replacing=job.nbytes(), owner=job.owner)
    job.data, job.background, job.target = data, background, target
    return job_info(job, state.store.ttl)


def _delete(which: str, job, state) -> JobInfo:
    job.set_arrays(**{which: None})
    return job_info(job, state.store.ttl)


@router.put("/data", response_model=JobInfo, summary="Upload the measured data", openapi_extra=_upload_body("data"),
            responses=errors(400, 401, 404, 413, 415, 422, 503, 507))
async def put_data(request: Request, job: JobDep, state: StateDep, body: BodyDep) -> JobInfo:
    """Set the job's measured projections (the objective's default target, minus the background)."""
    return await _put("data", request, body, job, state)


@router.delete("/data", response_model=JobInfo, summary="Remove the data", responses=errors(401, 404))
async def delete_data(job: JobDep, state: StateDep) -> JobInfo:
    return _delete("data", job, state)


@router.put("/background", response_model=JobInfo, summary="Upload the stationary background",
            openapi_extra=_upload_body("background"), responses=errors(400, 401, 404, 413, 415, 422, 503, 507))
async def put_background(request: Request, job: JobDep, state: StateDep, body: BodyDep) -> JobInfo:
    """Set the stationary background (e.g. container and liquid), subtracted from the job's data."""
    return await _put("background", request, body, job, state)


@router.delete("/background", response_model=JobInfo, summary="Remove the background", responses=errors(401, 404))
async def delete_background(job: JobDep, state: StateDep) -> JobInfo:
    return _delete("background", job, state)
