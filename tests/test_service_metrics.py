"""/metrics in the Prometheus text format."""

import re

import httpx

from service_support import client, p2d, server  # noqa: F401 - fixtures


def _value(text, name, labels=""):
    m = re.search(rf"^{re.escape(name + labels)} (\S+)$", text, re.M)
    assert m, f"{name}{labels} missing"
    return float(m.group(1))


def test_metrics_count_requests_jobs_memory_and_compute(server, client, p2d):  # noqa: F811
    before = httpx.get(f"{server.url}/metrics").text
    job = client.create_job(p2d.geometry, data=p2d.data, surfaces=p2d.init)
    job.objective(p2d.init)
    r = httpx.get(f"{server.url}/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    text = r.text
    for line in text.splitlines():  # every sample line is `name{labels} number`
        assert line.startswith("#") or re.match(r"^[a-z_]+(\{.*\})? -?[0-9.e+-]+$", line), line
    assert _value(text, "bubsub_jobs") >= 1
    assert _value(text, "bubsub_job_memory_bytes") >= p2d.data.nbytes
    assert _value(text, "bubsub_process_resident_memory_bytes") > 0
    assert _value(text, "bubsub_compute_seconds_total", '{op="objective"}') > 0
    assert _value(text, "bubsub_compute_calls_total", '{op="objective"}') >= 1
    route = '{method="POST",route="/v1/jobs/{job_id}/objective",status="200"}'
    assert _value(text, "bubsub_http_requests_total", route) >= 1
    assert job.id not in text  # routes are templates: job ids never leak
    assert _value(text, "bubsub_jobs_created_total") > _value(before, "bubsub_jobs_created_total")
    assert _value(text, "bubsub_ready") == 1
    job.delete()


def test_junk_methods_share_one_label_and_refusals_are_counted():
    """Issue 13: /metrics grew by a label per made-up HTTP method."""
    from service_support import ServerThread

    with ServerThread(max_body_bytes=4096) as s:
        for i in range(50):
            assert httpx.request(f"JUNK{i}", f"{s.url}/healthz").status_code == 405
        r = httpx.post(f"{s.url}/v1/jobs", content=b"x" * 5000, headers={"content-type": "application/json"})
        assert r.status_code == 413
        text = httpx.get(f"{s.url}/metrics").text
        assert "JUNK" not in text
        assert _value(text, "bubsub_http_requests_total", '{method="other",route="/healthz",status="405"}') == 50
        assert _value(text, "bubsub_requests_refused_total", '{reason="too_large"}') == 1
        methods = set(re.findall(r'method="([^"]*)"', text))
        assert methods <= {"GET", "HEAD", "POST", "PUT", "DELETE", "OPTIONS", "PATCH", "other"}, methods
