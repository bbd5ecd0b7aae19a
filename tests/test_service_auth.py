"""Bearer tokens: 401 without a valid one; a job is visible only to the token that created it."""

import httpx
import pytest

from bubsub.clients.remote.client import ProjectorClient
from service_support import ServerThread, p2d  # noqa: F401 - fixture


@pytest.fixture(scope="module")
def secured(tmp_path_factory):
    path = tmp_path_factory.mktemp("auth") / "tokens"
    path.write_text("# one token per line\nbeta-token\n\n")
    with ServerThread(tokens="alpha-token, gamma-token", tokens_file=path) as s:
        yield s


def test_tokens_required_on_v1_only(secured):
    assert httpx.get(f"{secured.url}/healthz").status_code == 200
    assert httpx.get(f"{secured.url}/readyz").status_code == 200
    assert httpx.get(f"{secured.url}/metrics").status_code == 200
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": "Basic YWxwaGE6eA=="},
                    {"Authorization": "Bearer"}, {"Authorization": "alpha-token"}):
        r = httpx.get(f"{secured.url}/v1/jobs", headers=headers)
        assert r.status_code == 401 and r.headers["www-authenticate"].startswith("Bearer"), headers
        assert r.json()["code"] == "unauthorized"
    # a body is not even read without a token
    r = httpx.post(f"{secured.url}/v1/jobs", content=b"{}", headers={"content-type": "application/json"})
    assert r.status_code == 401


def test_jobs_are_isolated_between_tokens(secured, p2d):  # noqa: F811
    alpha = ProjectorClient(secured.url, token="alpha-token")
    beta = ProjectorClient(secured.url, token="beta-token")  # from the token file
    job = alpha.create_job(p2d.geometry, data=p2d.data, surfaces=p2d.init)
    assert [j["id"] for j in alpha.jobs()] == [job.id]
    assert beta.jobs() == []
    for method, suffix in [("GET", ""), ("DELETE", ""), ("PUT", "/data"), ("POST", "/objective")]:
        r = beta._http.request(method, f"/v1/jobs/{job.id}{suffix}", content=b"x",
                               headers={"content-type": "application/x-npy"})
        assert r.status_code == 404 and r.json()["code"] == "unknown_job", (method, suffix)
    assert job.objective(p2d.init)[0] == p2d.projector.objective(p2d.init, p2d.data)[0]
    assert job.recreated == 0  # beta's attempts changed nothing
    job.delete()
    alpha.close()
    beta.close()
