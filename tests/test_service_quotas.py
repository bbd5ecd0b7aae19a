"""Per-token quotas: one token cannot fill the server and lock the others out.

Issue 13: the caps were shared across tokens, so one token could fill the server and
every other token got 507.
"""

import asyncio
import json
import threading

import httpx
import numpy as np
import pytest

from bubsub.bench.service_harness import npy, small_2d_job
from bubsub.service.compute import ComputePool
from bubsub.service.config import Settings
from bubsub.service.errors import APIError
from service_support import ServerThread

A = {"Authorization": "Bearer alpha"}
B = {"Authorization": "Bearer beta"}


def test_default_quotas_are_half_the_caps_with_several_tokens():
    s = Settings(max_jobs=100, max_memory_bytes=1 << 30, workers=2, max_queue=6)
    assert s.token_quotas(0) == (100, 1 << 30, 8)
    assert s.token_quotas(2) == (50, 1 << 29, 4)
    assert Settings(token_max_jobs=7).token_quotas(3)[0] == 7


def test_one_token_cannot_take_all_jobs():
    spec, _ = small_2d_job()
    with ServerThread(tokens="alpha,beta", token_max_jobs=3) as s:
        codes = [httpx.post(f"{s.url}/v1/jobs", json=spec, headers=A, timeout=60).status_code for _ in range(4)]
        assert codes == [201, 201, 201, 507]
        r = httpx.post(f"{s.url}/v1/jobs", json=spec, headers=A, timeout=60)
        assert r.json()["code"] == "token_quota" and "BUBSUB_TOKEN_MAX_JOBS" in r.json()["detail"]
        assert httpx.post(f"{s.url}/v1/jobs", json=spec, headers=B, timeout=60).status_code == 201


def test_one_token_cannot_take_all_memory():
    spec, g = small_2d_job()
    files = {"job": (None, json.dumps(spec), "application/json"),
             "data": ("d.npy", npy(np.zeros(g.shape, np.float32)), "application/x-npy")}
    with ServerThread(tokens="alpha,beta", max_memory_bytes=1 << 20, token_max_memory_bytes=10_000) as s:
        codes = []
        while len(codes) < 50 and (not codes or codes[-1] == 201):
            codes.append(httpx.post(f"{s.url}/v1/jobs", files=files, headers=A, timeout=60).status_code)
        assert codes[-1] == 507 and 1 < len(codes) < 50, codes
        r = httpx.post(f"{s.url}/v1/jobs", files=files, headers=A, timeout=60)
        assert r.json()["code"] == "token_quota" and "BUBSUB_TOKEN_MAX_MEMORY_BYTES" in r.json()["detail"]
        assert s.state.store.memory_bytes < (1 << 20)  # the server-wide cap was never the limit
        assert httpx.post(f"{s.url}/v1/jobs", files=files, headers=B, timeout=60).status_code == 201


def test_concurrent_computations_per_token():
    pool = ComputePool(workers=1, max_queue=8, retry_after=3, per_owner=2)
    gate = threading.Event()

    async def main():
        first = [asyncio.ensure_future(pool.run("x", gate.wait, owner="a")) for _ in range(2)]
        await asyncio.sleep(0.05)
        with pytest.raises(APIError) as e:
            await pool.run("x", gate.wait, owner="a")
        assert e.value.status == 503 and e.value.code == "token_busy" and e.value.headers["Retry-After"] == "3"
        other = asyncio.ensure_future(pool.run("x", gate.wait, owner="b"))  # another token still gets in
        await asyncio.sleep(0.05)
        gate.set()
        await asyncio.gather(*first, other)

    asyncio.run(main())
    pool.shutdown()
    assert pool.rejected_total == 1 and pool.pending == 0
