"""/healthz and /readyz."""

import httpx

from service_support import ServerThread, server  # noqa: F401 - fixture


def test_healthz_and_readyz(server):  # noqa: F811
    assert httpx.get(f"{server.url}/healthz").json() == {"status": "ok", "detail": None}
    r = httpx.get(f"{server.url}/readyz")
    assert r.status_code == 200 and r.json()["status"] == "ready"


def test_readyz_false_when_not_ready():
    with ServerThread(retry_after_seconds=4) as s:
        s.state.ready = False  # what shutdown does first
        r = httpx.get(f"{s.url}/readyz")
        assert r.status_code == 503 and r.json()["status"] == "not ready"
        assert r.headers["retry-after"] == "4"  # every 503 says when to come back
        assert httpx.get(f"{s.url}/healthz").status_code == 200


def test_unknown_route_and_method_are_json(server):  # noqa: F811
    r = httpx.get(f"{server.url}/nope")
    assert r.status_code == 404 and r.json()["code"] == "not_found"
    r = httpx.put(f"{server.url}/healthz")
    assert r.status_code == 405 and "detail" in r.json()


def test_docs_describe_binary_bodies(server):  # noqa: F811
    assert httpx.get(f"{server.url}/docs").status_code == 200
    spec = httpx.get(f"{server.url}/openapi.json").json()
    paths = spec["paths"]
    for op in ("forward", "vjp", "objective"):
        post = paths[f"/v1/jobs/{{job_id}}/{op}"]["post"]
        content = post["requestBody"]["content"]
        assert "application/x-npz" in content and "multipart/form-data" in content
        assert post["responses"]["200"]["content"]
    assert "application/x-npy" in paths["/v1/jobs/{job_id}/forward"]["post"]["requestBody"]["content"]
    assert "application/x-npy" in paths["/v1/jobs/{job_id}/data"]["put"]["requestBody"]["content"]
    create = paths["/v1/jobs"]["post"]["requestBody"]["content"]
    assert create["application/json"]["schema"]["$ref"] == "#/components/schemas/JobCreate"
    assert "JobCreate" in spec["components"]["schemas"]


def test_blas_threads_limited_while_serving():
    threadpoolctl = __import__("pytest").importorskip("threadpoolctl")

    def blas_threads():
        return [p["num_threads"] for p in threadpoolctl.threadpool_info() if p["user_api"] == "blas"]

    before = blas_threads()
    with ServerThread(blas_threads=1):
        assert blas_threads() and set(blas_threads()) == {1}
    assert blas_threads() == before
