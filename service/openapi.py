"""OpenAPI fragments for the binary request and response bodies, and the ``/docs`` page served offline."""

from __future__ import annotations

from fastapi import HTTPException, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse

from bubsub.service.codec import JSON, MULTIPART, NPY, NPZ
from bubsub.service.errors import error_responses
from bubsub.service.schemas import JobCreate

__all__ = ["binary_body", "binary_response", "job_create_body", "errors", "add_docs", "DOCS_ASSETS"]

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


#: Swagger UI's files that ``/docs`` loads, served by this server from the ``swagger-ui-bundle`` package (the
#: ``service`` extra): a beamline network is often offline, and a page that loads them from a CDN is blank there.
DOCS_ASSETS = {"swagger-ui-bundle.js": "text/javascript; charset=utf-8", "swagger-ui.css": "text/css; charset=utf-8",
               "favicon-32x32.png": "image/png"}


def add_docs(app, path="/docs"):
    """Serve Swagger UI at ``path`` with its script, style sheet and icon from this server (no external URL).

    FastAPI's own ``docs_url`` page loads them from a CDN; the app is made with
    ``docs_url=None`` and this adds ``GET path`` (the page) and
    ``GET path/NAME`` for the names in :data:`DOCS_ASSETS` (nothing else of the
    package is served). ReDoc is not served (``redoc_url=None``).

    Parameters
    ----------
    app : fastapi.FastAPI
    path : str
    """
    try:
        from swagger_ui_bundle import swagger_ui_path
    except ImportError:  # pragma: no cover - the service extra installs it
        swagger_ui_path = None

    @app.get(path, include_in_schema=False)
    async def docs_page(request: Request):
        root = request.scope.get("root_path", "").rstrip("/")
        if swagger_ui_path is None:
            return HTMLResponse(f"<p>The API page needs the swagger-ui-bundle package (pip install "
                                f"'bubsub[service]'); the API itself is described at "
                                f"<a href='{root}{app.openapi_url}'>{app.openapi_url}</a>.</p>", status_code=503)
        return get_swagger_ui_html(openapi_url=f"{root}{app.openapi_url}", title=f"{app.title} - API",
                                   swagger_js_url=f"{root}{path}/swagger-ui-bundle.js",
                                   swagger_css_url=f"{root}{path}/swagger-ui.css",
                                   swagger_favicon_url=f"{root}{path}/favicon-32x32.png")

    @app.get(path + "/{name}", include_in_schema=False)
    async def docs_asset(name: str):
        if swagger_ui_path is None or name not in DOCS_ASSETS:
            raise HTTPException(status_code=404, detail=f"no {path}/{name}")
        return FileResponse(swagger_ui_path / name, media_type=DOCS_ASSETS[name],
                            headers={"cache-control": "public, max-age=86400"})
