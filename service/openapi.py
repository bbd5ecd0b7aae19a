"""OpenAPI fragments for the binary request and response bodies."""

from __future__ import annotations

from .codec import JSON, MULTIPART, NPY, NPZ
from .errors import error_responses
from .schemas import JobCreate

__all__ = ["binary_body", "binary_response", "job_create_body", "errors"]

_BINARY = {"type": "string", "format": "binary"}


def binary_body(description, arrays, npy=True):
    """``openapi_extra`` for a body of arrays as ``.npy``, ``.npz`` or multipart.

    Parameters
    ----------
    description : str
    arrays : dict of str to str
        Array name -> description; a bare ``.npy`` body is the first array.
    npy : bool
        Whether a single ``.npy`` body is accepted.
    """
    content = {}
    first = next(iter(arrays))
    if npy:
        content[NPY] = {"schema": _BINARY, "x-bubsub-array": first}
    content[NPZ] = {"schema": _BINARY, "x-bubsub-arrays": list(arrays)}
    content[MULTIPART] = {
        "schema": {
            "type": "object",
            "properties": {k: {**_BINARY, "description": v} for k, v in arrays.items()},
            "required": [first],
        },
        "encoding": {k: {"contentType": NPY} for k in arrays},
    }
    lines = "\n".join(f"- `{k}`: {v}" for k, v in arrays.items())
    return {"requestBody": {"required": True, "description": f"{description}\n\n{lines}", "content": content}}


def binary_response(description, media=NPY):
    """``responses`` entry for a 200 with a binary body."""
    return {200: {"description": description, "content": {media: {"schema": _BINARY}}}}


def job_create_body():
    """``openapi_extra`` for POST /v1/jobs (JSON, or multipart with JSON metadata and arrays)."""
    ref = {"$ref": "#/components/schemas/JobCreate"}
    return {
        "requestBody": {
            "required": True,
            "description": (
                "Job metadata as JSON, or multipart/form-data with a `job` part (the same JSON) and optional "
                "`.npy` parts `vertices` (stacked initial control vertices of all surfaces, which also "
                "validates the control meshes), `data` and `background` (float arrays of the projection "
                "shape)."
            ),
            "content": {
                JSON: {"schema": ref},
                MULTIPART: {
                    "schema": {
                        "type": "object",
                        "required": ["job"],
                        "properties": {
                            "job": ref,
                            "vertices": {**_BINARY, "description": "(n_control_total, ndim) float"},
                            "data": {**_BINARY, "description": "measured projections"},
                            "background": {**_BINARY, "description": "stationary background projections"},
                        },
                    },
                    "encoding": {"job": {"contentType": JSON}, "vertices": {"contentType": NPY},
                                 "data": {"contentType": NPY}, "background": {"contentType": NPY}},
                },
            },
        }
    }


def errors(*statuses):
    """Documented JSON error responses."""
    return error_responses(*statuses)


#: models that only appear in hand-written request bodies and must be in the schema
EXTRA_MODELS = (JobCreate,)
