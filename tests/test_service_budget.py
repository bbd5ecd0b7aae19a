"""Compute memory budget: requests whose computation would not fit are refused before they run.

Issue 13: a job of a few kB with a 1 x 14000 x 14000 detector raised the server's
peak memory by 2.2 GB on one forward call; 20,000 2D surfaces at level 6 by 3.1 GB.
"""

import json

import httpx
import numpy as np
import pytest

from bubsub.bench.attacks import ServerProcess, npy, sphere_job
from bubsub.core import ScanGeometry
from bubsub.service.budget import OVERHEAD_BYTES, ComputeBudget
from bubsub.service.errors import APIError
from service_support import ServerThread

MiB = 1 << 20


@pytest.fixture(scope="module")
def capped():
    """Jobs (and so their computations) capped at 64 MiB."""
    with ServerThread(job_max_bytes=64 * MiB) as s:
        yield s


def test_huge_detector_refused_at_creation_with_the_limit_and_excess(capped):
    spec, _ = sphere_job(3000, 3000)  # 9 M pixels: a few kB of JSON
    r = httpx.post(f"{capped.url}/v1/jobs", json=spec, timeout=60)
    assert r.status_code == 413 and r.json()["code"] == "compute_too_large", r.text
    detail = r.json()["detail"]
    assert "9000000 output pixels" in detail and "BUBSUB_JOB_COMPUTE_MAX_BYTES" in detail and " by " in detail
    assert len(capped.state.store) == 0


def test_many_fine_surfaces_refused_at_creation(capped):
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 8, endpoint=False), pixel_size=1.0, cols=64)
    spec = {"geometry": {"kind": g.kind, "vectors": g.vectors.tolist(), "det_rows": None, "det_cols": 64},
            "surfaces": [{"n_control": 3, "levels": 6, "attenuation": 1.0, "count": 2000}]}
    r = httpx.post(f"{capped.url}/v1/jobs", json=spec, timeout=60)
    assert r.status_code == 413 and "384000 fine vertices" in r.json()["detail"], r.text


def test_server_wide_budget_507_when_never_fits_503_while_others_run():
    budget = ComputeBudget(1000, retry_after=2)
    with pytest.raises(APIError) as e:
        budget.reserve(1001)
    assert e.value.status == 507 and "by 1 bytes" in e.value.detail
    budget.reserve(700)
    with pytest.raises(APIError) as e:
        budget.reserve(400)
    assert e.value.status == 503 and e.value.headers["Retry-After"] == "2" and "100 bytes short" in e.value.detail
    budget.release(700)
    budget.reserve(400)
    assert budget.reserved == 400


def test_peak_memory_of_a_request_stays_within_the_job_cap():
    """The server's real peak RSS (a separate process) while it computes and while it refuses."""
    cap = 160 * MiB
    with ServerProcess(BUBSUB_JOB_MAX_BYTES=cap, BUBSUB_WORKERS=1) as srv, httpx.Client(timeout=120) as h:
        spec, x = sphere_job(1400, 1400)  # fits: about 2 M pixels, the sphere covers most of them
        spec["geometry"]["vectors"] = [[0, 1, 0, 0, 0, 0, 1.4 / 1400, 0, 0, 0, 0, 1.4 / 1400]]
        job = h.post(f"{srv.url}/v1/jobs", json=spec)
        assert job.status_code == 201, job.text
        base = srv.reset_peak()
        r = h.post(f"{srv.url}/v1/jobs/{job.json()['id']}/forward", content=npy(x),
                   headers={"content-type": "application/x-npy"})
        assert r.status_code == 200, r.text
        used = srv.peak() - base
        assert 10 * MiB < used <= cap + OVERHEAD_BYTES, used

        big, _ = sphere_job(4000, 4000)  # 16 M pixels: refused, and allocates nothing
        base = srv.reset_peak()
        r = h.post(f"{srv.url}/v1/jobs", json=big)
        assert r.status_code == 413 and r.json()["code"] == "compute_too_large"
        assert srv.peak() - base < 20 * MiB


def test_job_json_is_bounded_and_parsed_lists_are_limited():
    with ServerThread(max_json_bytes=64 << 10) as s:
        spec, _ = sphere_job(8, 8)
        spec["surfaces"][0]["faces"] = spec["surfaces"][0]["faces"] * 400  # ~ 100 kB of JSON
        r = httpx.post(f"{s.url}/v1/jobs", content=json.dumps(spec), headers={"content-type": "application/json"},
                       timeout=60)
        assert r.status_code == 413 and r.json()["code"] == "json_too_large"
        assert "BUBSUB_MAX_JSON_BYTES" in r.json()["detail"]
        spec, _ = sphere_job(8, 8)
        spec["geometry"]["vectors"][0] = spec["geometry"]["vectors"][0] * 100  # one row of 1200 numbers
        r = httpx.post(f"{s.url}/v1/jobs", json=spec, timeout=60)
        assert r.status_code == 422 and "at most 12" in r.json()["detail"], r.text
