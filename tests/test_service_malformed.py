"""Malformed input gets a 4xx JSON error (never a 500) and the connection stays open; poisoned data is refused.

Issue 13: .npy headers with negative or boolean dimensions, ragged face lists, face
indices beyond int64 and scan-file names with a NUL byte, a symlink loop or over
255 characters answered 500 and dropped the keep-alive connection; float64 data
above float32's range was stored as inf and every later objective failed.
"""

import json
import os

import httpx
import numpy as np
import pytest

from bubsub.bench.service_harness import keepalive_after, npy, raw_npy, small_2d_job, sphere_job
from service_support import ServerThread

NPY = "application/x-npy"


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    scans = tmp_path_factory.mktemp("scans")
    os.symlink("loop", scans / "loop")
    with ServerThread(scan_dir=scans) as s:
        yield s


@pytest.fixture(scope="module")
def job(srv):
    spec, g = small_2d_job()
    r = httpx.post(f"{srv.url}/v1/jobs", json=spec, timeout=60)
    assert r.status_code == 201
    return r.json()["id"], g


def _check(srv, method, path, body, ctype, status, code):
    got, kept = keepalive_after(srv.port, method, path, body, ctype)
    assert got == status, (path, got)
    assert kept, "the connection was closed after the error"
    r = httpx.request(method, f"{srv.url}{path}", content=body, headers={"content-type": ctype}, timeout=60)
    assert r.json()["code"] == code, r.text


@pytest.mark.parametrize("shape", ["(-1, 2)", "(True, 2)", "(2, -3)", "(1.5,)"])
def test_npy_header_with_bad_dimensions_400(srv, job, shape):
    _check(srv, "POST", f"/v1/jobs/{job[0]}/forward", raw_npy(shape, b"\0" * 16), NPY, 400, "bad_npy")


@pytest.mark.parametrize("face", [[0, 1], [0, 1, 2, 3], [0, 1, 2 ** 70], [0, 1, -2 ** 70]])
def test_ragged_or_huge_faces_422(srv, face):
    spec, _ = sphere_job(8, 8)
    spec["surfaces"][0]["faces"][3] = face
    _check(srv, "POST", "/v1/jobs", json.dumps(spec).encode(), "application/json", 422, "invalid")


@pytest.mark.parametrize("name", ["a\0b.npy", "loop", "x" * 300, "d/" * 200 + "x.npy"])
def test_bad_scan_file_names_422(srv, job, name):
    _check(srv, "PUT", f"/v1/jobs/{job[0]}/data", json.dumps({"file": name}).encode(), "application/json", 422,
           "bad_path")


def test_data_outside_float32_range_refused_and_job_stays_usable(srv, job):
    job_id, g = job
    url = f"{srv.url}/v1/jobs/{job_id}"
    r = httpx.put(f"{url}/data", content=npy(np.full(g.shape, 1e39)), headers={"content-type": NPY}, timeout=60)
    assert r.status_code == 422 and r.json()["code"] == "out_of_range" and "float32" in r.json()["detail"]
    ok = np.full(g.shape, 3e38, np.float32)
    assert httpx.put(f"{url}/data", content=npy(ok), headers={"content-type": NPY}, timeout=60).status_code == 200
    r = httpx.put(f"{url}/background", content=npy(-ok), headers={"content-type": NPY}, timeout=60)  # 6e38 overflows
    assert r.status_code == 422 and r.json()["code"] == "out_of_range"
    assert httpx.put(f"{url}/data", content=npy(np.ones(g.shape)), headers={"content-type": NPY}, timeout=60).status_code == 200
    a = 2 * np.pi * np.arange(6) / 6
    x = np.stack([np.cos(a), np.sin(a)], 1) * 5
    r = httpx.post(f"{url}/objective", content=npy(x), headers={"content-type": NPY}, timeout=60)
    assert r.status_code == 200 and np.isfinite(float(r.headers["x-objective"]))


def test_npz_with_many_members_refused_quickly(srv, job):
    import io
    import zipfile

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for i in range(5000):
            zf.writestr(f"m{i}.npy", npy(np.zeros(1)))
    r = httpx.post(f"{srv.url}/v1/jobs/{job[0]}/forward", content=buf.getvalue(),
                   headers={"content-type": "application/x-npz"}, timeout=60)
    assert r.status_code == 422 and "5000 members" in r.json()["detail"]
