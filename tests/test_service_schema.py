"""Schemathesis over the OpenAPI schema of a live server: no input gives a 5xx."""

import pytest
import schemathesis
from hypothesis import HealthCheck, settings

from bubsub.clients.remote.client import ProjectorClient
from service_support import phantom_2d, server  # noqa: F401 - fixture


@schemathesis.serializer("application/x-npy", "application/x-npz")
def _binary(ctx, value):
    """Generated binary bodies go out as they are (random bytes, mostly invalid arrays)."""
    if isinstance(value, bytes):
        return value
    return str(value).encode()


@pytest.fixture(scope="module")
def new_job(server):  # noqa: F811
    """Make a real job (so that generated requests reach past the 404)."""
    p = phantom_2d()
    c = ProjectorClient(server.url)
    yield lambda: c.create_job(p.geometry, data=p.data, surfaces=p.init).job_id
    c.close()


@pytest.fixture(scope="module")
def job_id(new_job):
    return new_job()


def _schema():
    from bubsub.service.app import create_app
    from bubsub.service.config import Settings

    return create_app(Settings()).openapi()  # the schema every server serves at /openapi.json


schema = schemathesis.openapi.from_dict(_schema())


@schema.parametrize()
@settings(max_examples=12, deadline=5000, derandomize=True,
          suppress_health_check=list(HealthCheck))
def test_no_server_errors(case, server, job_id, new_job):  # noqa: F811
    if "job_id" in (case.path_parameters or {}):
        deletes_job = case.method.upper() == "DELETE" and case.path == "/v1/jobs/{job_id}"
        case.path_parameters["job_id"] = new_job() if deletes_job else job_id
    response = case.call(base_url=server.url, timeout=10)
    assert response.status_code < 500, (case.method, case.path, response.status_code, response.text[:300])
    if response.status_code >= 400:
        body = response.json()
        assert body["code"] and body["detail"]
