"""Benchmark "attacks": bounded attacks on a projection server, and on another version of it.

``python -m bubsub.bench attacks [--before DIR] [--only NAME,...]``

Each attack starts its own server process on 127.0.0.1 (``python -m
bubsub.service``, small memory caps), measures the server's peak resident
memory rise (``VmHWM`` after resetting it through ``/proc/PID/clear_refs``)
and the worst ``/healthz`` latency while the attack runs, and records the
status codes the attack got. ``--before DIR`` runs every attack a second time
against the package found in ``DIR/bubsub`` (e.g. ``git archive REF``
unpacked there) and prints both side by side. The attacks are scaled to run
in about a minute each on a small machine; the full sizes are noted.
The server, its measurements and the request bodies are
:mod:`bubsub.bench.service_harness`.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import signal
import tempfile
import threading
import time
import zipfile
from collections import Counter
from pathlib import Path

import httpx
import numpy as np

from bubsub.bench.service_harness import (NPY, HealthProbe, MiB, ServerProcess, SlowClients, keepalive_after, npy,
                                          probe_health, raw_npy, small_2d_job, sphere_job)
from bubsub.core import ScanGeometry, sphere_surface

__all__ = ["ATTACKS", "run_attack", "format_table", "selected", "main"]


def _codes(responses):
    """Status codes in order of first appearance, with counts (``200 503x4``)."""
    c = Counter(r if isinstance(r, (int, str)) else r.status_code for r in responses)
    return " ".join(f"{k}x{n}" if n > 1 else str(k) for k, n in c.items())


# -- attacks --------------------------------------------------------------------------------
# Each takes a started ServerProcess (and its httpx client) and returns (codes, note).

def big_detector(srv, h):
    """A 1 x 8000 x 8000 detector, no data, one forward call (scaled down from a 14000 x 14000 one)."""
    spec, x = sphere_job(8000, 8000)
    r = h.post(f"{srv.url}/v1/jobs", json=spec)
    out = [r]
    if r.status_code == 201:
        out.append(h.post(f"{srv.url}/v1/jobs/{r.json()['id']}/forward", content=npy(x), headers=NPY))
    return out, ""


def many_surfaces(srv, h):
    """8000 2D triangles at subdivision level 6, vertices included (scaled down from 20,000)."""
    n = 8000
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 16, endpoint=False), pixel_size=1.0, cols=256)
    tri = np.array([[1.0, 0.0], [-0.5, 0.8], [-0.5, -0.8]]) * 0.05
    x = np.concatenate([tri + [(i % 100) * 0.2 - 10, (i // 100) * 0.2 - 8] for i in range(n)])
    spec = {"geometry": {"kind": g.kind, "vectors": g.vectors.tolist(), "det_rows": None, "det_cols": 256},
            "surfaces": [{"n_control": 3, "levels": 6, "attenuation": 1.0, "count": n}]}
    r = h.post(f"{srv.url}/v1/jobs", files={"job": (None, json.dumps(spec), "application/json"),
                                             "vertices": ("v.npy", npy(x), "application/x-npy")})
    out = [r]
    if r.status_code == 201:
        out.append(h.post(f"{srv.url}/v1/jobs/{r.json()['id']}/forward", content=npy(x), headers=NPY))
    return out, f"{len(npy(x)) / MiB:.1f} MiB of vertices"


def npz_members(srv, h):
    """One .npz with 30,000 members to /forward (scaled down from 95,000)."""
    spec, _ = small_2d_job()
    job = h.post(f"{srv.url}/v1/jobs", json=spec).json()["id"]
    buf = io.BytesIO()
    member = npy(np.zeros(1))
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for i in range(30_000):
            zf.writestr(f"m{i}.npy", member)
    body = buf.getvalue()
    r = h.post(f"{srv.url}/v1/jobs/{job}/forward", content=body, headers={"content-type": "application/x-npz"})
    return [r], f"{len(body) / MiB:.1f} MiB body"


def json_amplification(srv, h):
    """16 MiB of job JSON, nearly all control faces (scaled down from 64 MiB)."""
    faces = "[" + ",".join(["[1000,2000,3000]"] * (16 * MiB // 17)) + "]"
    spec, _ = sphere_job(8, 8)
    body = json.dumps(spec).replace(json.dumps(spec["surfaces"][0]["faces"]), faces)
    r = h.post(f"{srv.url}/v1/jobs", content=body.encode(), headers={"content-type": "application/json"})
    return [r], f"{len(body) / MiB:.0f} MiB JSON"


def malformed(srv, h):
    """Negative/boolean .npy dimensions, ragged faces, indices beyond int64, bad scan-file names."""
    spec, _ = small_2d_job()
    job = h.post(f"{srv.url}/v1/jobs", json=spec).json()["id"]
    bad_faces, _ = sphere_job(8, 8)
    ragged = json.loads(json.dumps(bad_faces))
    ragged["surfaces"][0]["faces"][0] = [0, 1]
    huge = json.loads(json.dumps(bad_faces))
    huge["surfaces"][0]["faces"][0] = [0, 1, 2 ** 70]

    def req(method, path, body, ctype):
        return method, path, body, ctype

    cases = [
        req("POST", f"/v1/jobs/{job}/forward", raw_npy("(-1, 2)"), "application/x-npy"),
        req("POST", f"/v1/jobs/{job}/forward", raw_npy("(True, 2)", b"\0" * 16), "application/x-npy"),
        req("POST", "/v1/jobs", json.dumps(ragged).encode(), "application/json"),
        req("POST", "/v1/jobs", json.dumps(huge).encode(), "application/json"),
        req("PUT", f"/v1/jobs/{job}/data", b'{"file": "a\\u0000b.npy"}', "application/json"),
        req("PUT", f"/v1/jobs/{job}/data", b'{"file": "loop"}', "application/json"),
        req("PUT", f"/v1/jobs/{job}/data", json.dumps({"file": "x" * 300}).encode(), "application/json"),
    ]
    codes, dropped = [], []
    for k, c in enumerate(cases):
        status, alive = keepalive_after(srv.port, *c)
        codes.append(status)
        if not alive:
            dropped.append(k)
    return codes, f"keep-alive kept {len(cases) - len(dropped)}/{len(cases)}" + (f" (lost: {dropped})" if dropped else "")


def float_range(srv, h):
    """float64 data above float32's range, then an objective (stored as float32 it would be inf and poison the job)."""
    spec, g = small_2d_job()
    job = h.post(f"{srv.url}/v1/jobs", json=spec).json()["id"]
    r1 = h.put(f"{srv.url}/v1/jobs/{job}/data", content=npy(np.full(g.shape, 1e39)), headers=NPY)
    a = 2 * np.pi * np.arange(6) / 6
    x = np.stack([np.cos(a), np.sin(a)], 1) * 5
    r2 = h.post(f"{srv.url}/v1/jobs/{job}/objective", content=npy(x), headers=NPY)
    return [r1, r2], "PUT data, then objective"


def slow_clients(srv, h, reconnect=False):
    """300 connections that never finish their request head, server limited to 256 descriptors; health
    probes and normal requests meanwhile."""
    with SlowClients(srv.port, 300, reconnect=reconnect) as attack:
        time.sleep(1.0)  # all connected (or queued)
        probes = []
        prober = threading.Thread(target=lambda: probes.extend(probe_health(srv.url, 8)))
        prober.start()
        codes = []
        end = time.monotonic() + 8
        while time.monotonic() < end:  # normal requests while the slow ones press on
            try:
                r = httpx.get(f"{srv.url}/v1/jobs", timeout=2)
                codes.append(r.status_code if r.status_code != 503 or "retry-after" not in r.headers
                             else "503+Retry-After")
            except httpx.HTTPError:
                codes.append("fail")
            time.sleep(0.2)
        prober.join()
    ok = sum(c == 200 for c in codes)
    health_ok = sum(st == 200 for _, st, _ in probes)
    worst = max(dt for _, _, dt in probes)
    return codes, (f"{attack.opened} slow connections opened, {attack.closed} closed by the server; {ok}/{len(codes)} "
                   f"normal requests 200; health probes {health_ok}/{len(probes)} 200, worst {1e3 * worst:.0f} ms")


def slow_clients_reconnecting(srv, h):
    """As slow_clients, each connection opened again as soon as the server closes it."""
    return slow_clients(srv, h, reconnect=True)


def junk_methods(srv, h):
    """300 requests with made-up HTTP methods, then the size of /metrics."""
    before = h.get(f"{srv.url}/metrics").text.count("\n")
    codes = [h.request(f"X{i:04d}", f"{srv.url}/healthz").status_code for i in range(300)]
    after = h.get(f"{srv.url}/metrics").text.count("\n")
    return codes, f"/metrics grew by {after - before} lines"


def token_quota(srv, h):
    """Token A fills the server with jobs; then token B tries to create one."""
    spec, g = small_2d_job()
    spec["geometry"]["vectors"] = spec["geometry"]["vectors"] * 128  # 1024 angles: 128 kB projections
    data = npy(np.zeros((1024, 32), np.float32))
    a = {"authorization": "Bearer alpha"}
    filled = 0
    while filled < 200:
        r = h.post(f"{srv.url}/v1/jobs", headers=a, files={"job": (None, json.dumps(spec), "application/json"),
                                                            "data": ("d.npy", data, "application/x-npy")})
        if r.status_code != 201:
            break
        filled += 1
    rb = h.post(f"{srv.url}/v1/jobs", headers={"authorization": "Bearer beta"},
                files={"job": (None, json.dumps(spec), "application/json"), "data": ("d.npy", data, "application/x-npy")})
    return [r, rb], f"token A created {filled} jobs, then got {r.status_code}; token B got {rb.status_code}"


def shutdown_timeout(srv, h):
    """SIGTERM during a long computation, with a 1 s shutdown timeout."""
    g = ScanGeometry.cone(np.linspace(0, 2 * np.pi, 96, endpoint=False), source_origin=150.0, origin_detector=50.0,
                          pixel_size=0.3, cols=96, rows=96)
    s = sphere_surface((0.0, 0.0, 0.0), 4.0, 1.0)
    spec = {"geometry": {"kind": g.kind, "vectors": g.vectors.tolist(), "det_rows": 96, "det_cols": 96},
            "surfaces": [{"n_control": len(s.control.vertices), "faces": np.asarray(s.control_faces).tolist(),
                          "levels": 3, "attenuation": 1.0}], "supersampling": 8}
    job = h.post(f"{srv.url}/v1/jobs", json=spec).json()["id"]
    out = {}

    def call():
        try:
            r = httpx.post(f"{srv.url}/v1/jobs/{job}/forward", content=npy(s.control.vertices), headers=NPY,
                           timeout=120)
            out["r"] = f"{r.status_code}" + (f" Retry-After {r.headers['retry-after']}"
                                             if "retry-after" in r.headers else "")
        except httpx.HTTPError as exc:
            out["r"] = type(exc).__name__

    t = threading.Thread(target=call)
    t.start()
    time.sleep(1.0)
    srv.proc.send_signal(signal.SIGTERM)
    t.join(120)
    return [out.get("r", "none")], "in-flight forward"


#: name -> (attack, extra server settings, whether /healthz is probed)
ATTACKS = {
    "big_detector": (big_detector, {}, True),
    "many_surfaces": (many_surfaces, {}, True),
    "npz_members": (npz_members, {}, True),
    "json_amplification": (json_amplification, {}, True),
    "malformed": (malformed, {"BUBSUB_SCAN_DIR": "{scan_dir}"}, False),
    "float_range": (float_range, {}, False),
    "slow_clients": (slow_clients, {"nofile": 256}, False),
    "slow_clients_reconnecting": (slow_clients_reconnecting, {"nofile": 256}, False),
    "junk_methods": (junk_methods, {}, False),
    "token_quota": (token_quota, {"BUBSUB_TOKENS": "alpha,beta", "BUBSUB_MAX_MEMORY_BYTES": str(16 * MiB)}, False),
    "shutdown_timeout": (shutdown_timeout, {"BUBSUB_SHUTDOWN_TIMEOUT_SECONDS": "1", "BUBSUB_WORKERS": "1",
                                            "BUBSUB_BACKEND": "embreex",
                                            "BUBSUB_JOB_COMPUTE_MAX_BYTES": str(4 << 30),
                                            "BUBSUB_MAX_COMPUTE_BYTES": str(4 << 30)}, False),
}


def run_attack(name, src=None, scan_dir=None):
    """Run one attack on a fresh server; returns a dict of codes, note, memory rise (MB), worst health (s)."""
    fn, extra, probe = ATTACKS[name]
    env = {k: (v.format(scan_dir=scan_dir) if isinstance(v, str) else v) for k, v in extra.items()}
    nofile = env.pop("nofile", None)
    with ServerProcess(src, nofile=nofile, **env) as srv, httpx.Client(timeout=120) as h:
        base = srv.reset_peak()
        health = HealthProbe(srv.url) if probe else contextlib.nullcontext()
        t0 = time.perf_counter()
        with health:
            responses, note = fn(srv, h)
        seconds = time.perf_counter() - t0
        rise = (srv.peak() - base) / 1e6 if srv.proc.poll() is None else float("nan")
    return {"attack": name, "codes": _codes(responses), "note": note, "rise_mb": rise, "seconds": seconds,
            "health_s": health.worst if probe else None}


def _cell(r):
    health = "" if r["health_s"] is None else f", /healthz worst {1e3 * r['health_s']:.0f} ms"
    note = f"; {r['note']}" if r["note"] else ""
    return f"{r['codes']}; +{r['rise_mb']:.0f} MB{health}{note}"


def format_table(rows):
    """Markdown table: attack | before | after (or attack | result)."""
    both = any("before" in r for r in rows)
    lines = ["| attack | before | after |" if both else "| attack | result |",
             "| --- | --- | --- |" if both else "| --- | --- |"]
    for r in rows:
        if both:
            lines.append(f"| {r['attack']} | {_cell(r['before'])} | {_cell(r['after'])} |")
        else:
            lines.append(f"| {r['attack']} | {_cell(r['after'])} |")
    return "\n".join(lines)


def selected(parser, only, known):
    """The names of a comma-separated ``--only`` (all of ``known`` when None); a parser error for unknown ones."""
    names = only.split(",") if only else list(known)
    unknown = sorted(set(names) - set(known))
    if unknown:
        parser.error(f"unknown names {unknown}; choose from {', '.join(known)}")
    return names


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m bubsub.bench attacks", description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", help="directory with the old 'bubsub' package to compare against")
    parser.add_argument("--only", help="comma-separated attacks (default: all): " + ", ".join(ATTACKS))
    parser.add_argument("--json", help="also write the results to this file")
    args = parser.parse_args(argv)
    names = selected(parser, args.only, ATTACKS)
    rows = []
    with tempfile.TemporaryDirectory() as scan_dir:
        os.symlink("loop", Path(scan_dir, "loop"))  # a symlink loop for the malformed-path attack
        for name in names:
            row = {"attack": name}
            if args.before:
                row["before"] = run_attack(name, args.before, scan_dir)
            row["after"] = run_attack(name, None, scan_dir)
            print(f"{name}: " + " | ".join(f"{k}: {_cell(v)}" for k, v in row.items() if k != "attack"),
                  flush=True)
            rows.append(row)
    print()
    print(format_table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0
