"""A bounded load test: more clients than workers and queue; the client's retries absorb the 503s."""

import threading
import time

import httpx

from bubsub.clients.remote.client import ProjectorClient
from service_support import ServerThread, phantom_2d


def test_eight_clients_on_one_worker_all_succeed_and_health_stays_fast():
    p = phantom_2d()
    with ServerThread(workers=1, max_queue=2) as s:
        with ProjectorClient(s.url) as c:
            job = c.create_job(p.geometry, data=p.data, surfaces=p.init)
        job.client = ProjectorClient(s.url, retry_timeout=60, backoff=0.02)  # shared: httpx is thread-safe
        expected = job.objective(p.init)[0]
        values, worst, stop = [], [0.0], threading.Event()

        def fit_like():
            for _ in range(5):
                values.append(job.objective(p.init)[0])

        def probe():
            with httpx.Client(timeout=30) as h:
                while not stop.is_set():
                    t0 = time.perf_counter()
                    assert h.get(f"{s.url}/healthz").status_code == 200
                    worst[0] = max(worst[0], time.perf_counter() - t0)
                    time.sleep(0.02)

        prober = threading.Thread(target=probe)
        prober.start()
        clients = [threading.Thread(target=fit_like) for _ in range(8)]
        for t in clients:
            t.start()
        for t in clients:
            t.join(120)
        stop.set()
        prober.join()
        job.client.close()
        assert len(values) == 40 and set(values) == {expected}
        assert s.state.pool.rejected_total > 0  # the queue did overflow: the retries were exercised
        assert worst[0] < 1.0, worst[0]
