"""The compute deadline is kept whatever the call's shape: within one heavy view, in the gradient, on the server.

The kernels read a stop flag that a watchdog thread sets at the deadline; a call of a single view that
takes seconds stops within a fraction of a second of it. Before, the deadline was checked only between
chunks of views, so such a call ran to its end (and the server answered 200 long past its timeout).
"""

import time

import httpx
import numpy as np
import pytest

from bubsub.core import MeshProjector, ScanGeometry, sphere_surface
from bubsub.core.projection.backends import available_backends
from bubsub.core.projection.backends.base import stop_flag
from bubsub.core.projection.projector import DeadlineExceeded
from service_support import ServerThread

SUPERSAMPLING = 8
BUBBLE = [sphere_surface((0.0, 0.0, 0.0), 9.0, 1.0, levels=3)]  # covers most of the detector


def one_view(det):
    """One cone-beam view of ``det`` x ``det`` pixels whose lattice (at supersampling 8) the bubble fills."""
    return ScanGeometry.cone(np.array([0.3]), source_origin=150.0, origin_detector=50.0, pixel_size=40.0 / det,
                             cols=det, rows=det)


def _call(projector, op, deadline=None):
    shape = projector.geometry.shape
    if op == "forward":
        return projector.forward(BUBBLE, deadline=deadline)
    if op == "vjp":
        return projector.vjp(BUBBLE, np.ones(shape, np.float32), deadline=deadline)
    return projector.objective(BUBBLE, np.zeros(shape, np.float32), deadline=deadline)


@pytest.fixture(scope="module")
def full_seconds():
    """Per operation, what a call on the 512 x 512 view takes: four times a 256 x 256 view's (the lattice
    points it visits), measured warm on one thread."""
    quarter = MeshProjector(one_view(256), supersampling=SUPERSAMPLING, threads=1, backend="raster")
    out = {}
    for op in ("forward", "vjp", "objective"):
        _call(quarter, op)  # warm
        t0 = time.perf_counter()
        _call(quarter, op)
        out[op] = 4 * (time.perf_counter() - t0)
    return out


def _deadline_for(full):
    """A deadline a quarter of the way into a call that takes ``full`` s (at most 0.3 s), and the latest it
    may end: the deadline plus a third of the call or 0.1 s, far sooner than running to its end."""
    d = min(0.3, full / 4)
    return d, d + max(0.1, full / 3)


def test_the_watchdog_sets_a_stop_flag_at_its_deadline():
    t0 = time.monotonic()
    flag = stop_flag(t0 + 0.05)
    assert flag[0] == 0
    while flag[0] == 0 and time.monotonic() < t0 + 2:
        time.sleep(0.001)
    took = time.monotonic() - t0
    assert flag[0] == 1 and 0.05 <= took < 0.5, took
    assert stop_flag(t0 - 1)[0] == 1  # already past: set at once
    never = stop_flag(None)
    time.sleep(0.06)
    assert never[0] == 0


@pytest.mark.parametrize("op", ["forward", "vjp", "objective"])
def test_a_single_heavy_view_stops_at_its_deadline(op, full_seconds):
    """One view, one thread: no chunk of views to stop between; the kernel itself stops."""
    full = full_seconds[op]
    deadline, latest = _deadline_for(full)
    P = MeshProjector(one_view(512), supersampling=SUPERSAMPLING, threads=1, backend="raster")
    t0 = time.perf_counter()
    with pytest.raises(DeadlineExceeded):
        _call(P, op, deadline=time.monotonic() + deadline)
    took = time.perf_counter() - t0
    assert took < latest, (op, took, deadline, full)


@pytest.mark.parametrize("backend", ["native", "embreex"])
def test_ray_casters_stop_within_a_view(backend):
    if backend not in available_backends():
        pytest.skip(f"{backend} backend not available here")
    # 512 x 512 pixels at 4 x 4 sub-rays: 4 million rays, some seconds of casting on any machine
    P = MeshProjector(one_view(512), supersampling=4, threads=1, backend=backend)
    small = MeshProjector(one_view(64), supersampling=4, threads=1, backend=backend)
    small.forward(BUBBLE)  # warm
    t0 = time.perf_counter()
    small.forward(BUBBLE)
    full = 64 * (time.perf_counter() - t0)  # 64 times the rays
    deadline, latest = _deadline_for(full)
    t0 = time.perf_counter()
    with pytest.raises(DeadlineExceeded):
        P.forward(BUBBLE, deadline=time.monotonic() + deadline)
    took = time.perf_counter() - t0
    assert took < latest, (took, deadline, full)


def test_the_server_answers_504_within_a_fraction_of_the_timeout(full_seconds):
    """forward, vjp and objective of a one-view job heavier than its timeout: one-line JSON 504s soon after."""
    g = one_view(512)
    timeout, _ = _deadline_for(min(full_seconds.values()))
    spec = {"geometry": {"kind": g.kind, "vectors": g.vectors.tolist(), "det_rows": g.det_rows,
                         "det_cols": g.det_cols},
            "surfaces": [{"n_control": 42, "faces": np.asarray(BUBBLE[0].control_faces).tolist(), "levels": 3,
                          "attenuation": 1.0}],
            "supersampling": SUPERSAMPLING, "compute_timeout_seconds": round(timeout, 3)}
    import io

    def npz(**arrays):
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        return buf.getvalue()

    x = BUBBLE[0].vertices
    bodies = {"forward": npz(vertices=x), "vjp": npz(vertices=x, residual=np.ones(g.shape, np.float32)),
              "objective": npz(vertices=x, data=np.zeros(g.shape, np.float32))}
    with ServerThread(workers=1, compute_timeout_seconds=30, projector_threads=1, job_compute_max_bytes=2 << 30,
                      max_compute_bytes=2 << 30) as server:
        r = httpx.post(f"{server.url}/v1/jobs", json=spec, timeout=30)
        assert r.status_code == 201, r.text
        job = r.json()["id"]
        for op, body in bodies.items():
            t0 = time.perf_counter()
            r = httpx.post(f"{server.url}/v1/jobs/{job}/{op}", content=body,
                           headers={"content-type": "application/x-npz"}, timeout=60)
            took = time.perf_counter() - t0
            assert r.status_code == 504 and r.json()["code"] == "compute_timeout", (op, r.status_code, r.text[:200])
            assert "\n" not in r.text and f"{op} stopped after its compute timeout" in r.json()["detail"]
            # the whole call takes seconds; a 1 MB body, the estimate and the HTTP round trip some hundredths
            # (tenths on a machine with many more busy threads than cores)
            assert took < timeout + 0.7, (op, took, timeout, full_seconds[op])
        assert server.state.pool.timeouts_total == 3 and server.state.pool.running == 0


def test_projector_report_names_the_server_and_the_remote_phases():
    from bubsub.clients.pipeline.reconstruct import merged_projector_report, projector_report

    class Remote:
        server = "http://127.0.0.1:8123"

    phases = ["preview", "initial_bubbles", "radius_estimation", "fit", "topology", "validity", "refine"]
    remote = projector_report(Remote(), phases, "raster")
    assert remote == {"server": "http://127.0.0.1:8123", "remote_phases": ["fit"],
                      "local_phases": ["preview", "initial_bubbles", "radius_estimation", "topology", "validity",
                                       "refine"], "local_backend": "raster"}
    local = projector_report(None, phases, "native")
    assert local["server"] is None and local["remote_phases"] == [] and local["local_phases"] == phases
    # slabs: a slab that had no fit (no bubbles) adds its phases; the server is the one named
    other = projector_report(Remote(), ["preview", "holdout"], "raster")
    merged = merged_projector_report([remote, None, other])
    assert merged["server"] == Remote.server and merged["remote_phases"] == ["fit"]
    assert merged["local_phases"] == remote["local_phases"] + ["holdout"]
    assert merged_projector_report([None]) is None
