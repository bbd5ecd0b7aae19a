"""Request bodies turned into job specs and arrays, in the decoding pool.

Everything here is synchronous and CPU-bound (JSON parsing, multipart
splitting, ``.npy``/``.npz`` headers, zip directories); routes call it with
``await state.decoder.run(...)`` so that a large or pathological body never
stalls the event loop (and with it ``/healthz`` and every other request).
"""

from __future__ import annotations

from pydantic import ValidationError

from bubsub.service.codec import JSON, MULTIPART, NPY, NPZ, decode_arrays, decode_npy, parse_multipart
from bubsub.service.errors import APIError
from bubsub.service.schemas import DataFile, JobCreate

__all__ = ["JOB_PARTS", "check_json_size", "parse_spec", "decode_job_body", "decode_compute_body",
           "decode_upload_body"]

#: parts of a multipart POST /v1/jobs body
JOB_PARTS = ("job", "vertices", "data", "background")


def check_json_size(raw, limit, what="job metadata"):
    """413 for a JSON document over ``BUBSUB_MAX_JSON_BYTES`` (checked before it is parsed)."""
    if len(raw) > limit:
        raise APIError(413, f"{what} is {len(raw)} bytes of JSON, over the {limit}-byte limit "
                            f"(BUBSUB_MAX_JSON_BYTES) by {len(raw) - limit} bytes", "json_too_large")


def parse_spec(raw: bytes) -> JobCreate:
    """:class:`JobCreate` from JSON bytes (400 for bad JSON, 422 for invalid metadata)."""
    try:
        return JobCreate.model_validate_json(raw)
    except ValidationError as exc:
        errs = exc.errors()
        if any(e["type"] == "json_invalid" for e in errs):
            raise APIError(400, f"job metadata is not valid JSON: {errs[0]['msg']}", "bad_json") from None
        msgs = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'job'}: {e['msg']}" for e in errs[:10])
        raise APIError(422, f"invalid job metadata: {msgs}", "invalid") from None


def decode_job_body(body, ctype, params, max_json_bytes):
    """``(spec, arrays)`` of a POST /v1/jobs body (JSON, or multipart with a ``job`` part and arrays)."""
    arrays = {}
    if ctype == JSON:
        raw = body
    elif ctype == MULTIPART:
        parts = {}
        for part in parse_multipart(body, params.get("boundary"), max_parts=len(JOB_PARTS)):
            if part.name not in JOB_PARTS:
                raise APIError(422, f"unexpected multipart part {part.name!r}; expected {list(JOB_PARTS)}",
                               "unknown_array")
            if part.name in parts:
                raise APIError(400, f"multipart part {part.name!r} given twice", "bad_multipart")
            parts[part.name] = part
        if "job" not in parts:
            raise APIError(422, "multipart body needs a 'job' part with the JSON metadata", "invalid")
        raw = parts.pop("job").data
        arrays = {name: decode_npy(p.data, name) for name, p in parts.items()}
    else:
        raise APIError(415, f"unsupported Content-Type {ctype or '(none)'!r}; send {JSON} or {MULTIPART} "
                            f"(a 'job' JSON part and .npy parts)", "unsupported_media_type")
    check_json_size(raw, max_json_bytes)
    return parse_spec(raw), arrays


def decode_compute_body(body, ctype, params, max_bytes, allowed, required):
    """Named arrays of a compute request (422 when a required one is missing)."""
    arrays = decode_arrays(body, ctype, params, max_bytes, allowed)
    missing = [k for k in required if k not in arrays]
    if missing:
        raise APIError(422, f"missing arrays {missing}; send {NPZ} or multipart with {list(allowed)}",
                       "missing_array")
    return arrays


def decode_upload_body(body, ctype, which, max_json_bytes):
    """An uploaded array (``.npy``) or a :class:`DataFile` reference (JSON)."""
    if ctype == NPY:
        return decode_npy(body, which)
    if ctype == JSON:
        check_json_size(body, max_json_bytes, "the file reference")
        try:
            return DataFile.model_validate_json(body)
        except ValidationError as exc:
            raise APIError(422, f"invalid file reference: {exc.errors()[0]['msg']}", "invalid") from None
    raise APIError(415, f"unsupported Content-Type {ctype or '(none)'!r}; send {NPY} (or {JSON} naming a "
                        f"file in the scan directory)" + ("; one array only, not .npz" if ctype == NPZ else ""),
                   "unsupported_media_type")
