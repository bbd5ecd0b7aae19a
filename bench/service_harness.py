"""A projection server in a child process, and the requests and clients the service benchmarks send it.

:class:`ServerProcess` runs ``python -m bubsub.service`` on a free loopback port
with small memory caps (:data:`BASE_ENV`) and measures its peak resident
memory; :class:`HealthProbe` polls ``/healthz`` meanwhile; :func:`npy`,
:func:`raw_npy`, :func:`sphere_job` and :func:`small_2d_job` build request
bodies; :func:`keepalive_after`, :func:`raw_request`, :class:`SlowClients` and
:func:`probe_health` talk to the server below httpx's level. Used by
:mod:`bubsub.bench.attacks`, :mod:`bubsub.bench.admission`,
:mod:`bubsub.bench.deadline` and the service's tests.
"""

from __future__ import annotations

import http.client
import io
import os
import re
import resource
import selectors
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

from bubsub.core import ScanGeometry, sphere_surface

__all__ = ["MiB", "BASE_ENV", "ServerProcess", "HealthProbe", "npy", "raw_npy", "NPY", "sphere_job", "small_2d_job",
           "keepalive_after", "raw_request", "read_until_closed", "SlowClients", "probe_health"]

MiB = 1 << 20


#: caps of the attacked servers (small, so that refusals and damage show quickly)
BASE_ENV = {
    "BUBSUB_WORKERS": "2",
    "BUBSUB_LOG_LEVEL": "critical",
    "BUBSUB_JOB_MAX_BYTES": str(256 * MiB),
    "BUBSUB_MAX_MEMORY_BYTES": str(512 * MiB),
    "BUBSUB_MAX_COMPUTE_BYTES": str(1024 * MiB),
    "BUBSUB_HEADER_TIMEOUT_SECONDS": "2",
    "BUBSUB_BODY_TIMEOUT_SECONDS": "5",
}


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerProcess:
    """``python -m bubsub.service`` on a free loopback port, with its memory measured.

    Parameters
    ----------
    src : str or None
        Directory holding the ``bubsub`` package to run (None: the installed one).
    nofile : int, optional
        File-descriptor limit of the server.
    **env
        ``BUBSUB_*`` settings on top of :data:`BASE_ENV`.
    """

    def __init__(self, src=None, nofile=None, **env):
        self.port = _free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        full = {**os.environ, **BASE_ENV, **{k: str(v) for k, v in env.items()}}
        if src:
            full["PYTHONPATH"] = os.pathsep.join([str(src), full.get("PYTHONPATH", "")]).rstrip(os.pathsep)

        def limits():
            if nofile:
                resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, nofile))

        self.proc = subprocess.Popen([sys.executable, "-m", "bubsub.service", "--host", "127.0.0.1", "--port",
                                      str(self.port)], env=full, preexec_fn=limits, cwd=tempfile.gettempdir(),
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        end = time.monotonic() + 120
        while True:
            try:
                if httpx.get(f"{self.url}/readyz", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if self.proc.poll() is not None or time.monotonic() > end:
                raise RuntimeError(f"server did not start: {self.proc.stderr.read().decode()[-2000:]}")
            time.sleep(0.1)

    def _status(self, key):
        text = Path(f"/proc/{self.proc.pid}/status").read_text()
        return int(re.search(rf"^{key}:\s+(\d+) kB", text, re.M).group(1)) * 1024

    def reset_peak(self):
        """Start a new peak-RSS measurement; returns the current RSS."""
        Path(f"/proc/{self.proc.pid}/clear_refs").write_text("5")
        return self._status("VmRSS")

    def peak(self):
        """Peak RSS since :meth:`reset_peak` (bytes)."""
        return self._status("VmHWM")

    def stop(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


class HealthProbe:
    """Polls ``/healthz`` in a thread; ``worst`` is the slowest answer (s), ``failed`` the failures."""

    def __init__(self, url, interval=0.05):
        self.url, self.interval = url, interval
        self.worst, self.failed, self.count = 0.0, 0, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        with httpx.Client(timeout=30) as h:
            while not self._stop.is_set():
                t0 = time.perf_counter()
                try:
                    ok = h.get(f"{self.url}/healthz").status_code == 200
                except httpx.HTTPError:
                    ok = False
                self.worst = max(self.worst, time.perf_counter() - t0)
                self.failed += not ok
                self.count += 1
                time.sleep(self.interval)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        end = time.monotonic() + 30
        while self.count < 3 and time.monotonic() < end:  # a few probes even if the attack was quick
            time.sleep(0.02)
        self._stop.set()
        self._thread.join(60)


def npy(a):
    """The bytes of ``a`` as a ``.npy`` file (no pickles)."""
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def raw_npy(shape_literal, payload=b""):
    """A ``.npy`` file whose header declares ``shape_literal`` verbatim."""
    head = f"{{'descr': '<f8', 'fortran_order': False, 'shape': {shape_literal}, }}".encode()
    head += b" " * (63 - (10 + len(head)) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + len(head).to_bytes(2, "little") + head + payload

NPY = {"content-type": "application/x-npy"}


def sphere_job(rows, cols, n_angles=1, supersampling=1):
    """JSON of a 3D parallel job with one 42-vertex sphere, and its control vertices."""
    g = ScanGeometry.parallel(np.linspace(0, np.pi, n_angles, endpoint=False), pixel_size=0.01, cols=cols,
                              rows=rows)
    s = sphere_surface((0, 0, 0), 1.0, 0.1)
    spec = {"geometry": {"kind": g.kind, "vectors": g.vectors.tolist(), "det_rows": rows, "det_cols": cols},
            "surfaces": [{"n_control": len(s.control.vertices), "faces": np.asarray(s.control_faces).tolist(),
                          "levels": s.levels, "attenuation": 0.1}], "supersampling": supersampling}
    return spec, s.control.vertices


def small_2d_job():
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 8, endpoint=False), pixel_size=1.0, cols=32)
    return {"geometry": {"kind": g.kind, "vectors": g.vectors.tolist(), "det_rows": None, "det_cols": 32},
            "surfaces": [{"n_control": 6, "levels": 2, "attenuation": 1.0}]}, g


def keepalive_after(port, method, path, body, ctype):
    """Send one request, then GET /healthz on the same connection.

    Returns
    -------
    status : int
        Status of the first request.
    kept : bool
        Whether the second request was answered 200 on the same socket.
    """
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        conn.request(method, path, body=body, headers={"Content-Type": ctype})
        r = conn.getresponse()
        r.read()
        sock = conn.sock
        if r.will_close or sock is None:
            return r.status, False
        try:
            conn.request("GET", "/healthz")
            second = conn.getresponse()
            second.read()
        except (OSError, http.client.HTTPException):
            return r.status, False
        return r.status, second.status == 200 and conn.sock is sock
    finally:
        conn.close()


def raw_request(port, data):
    """A socket to ``127.0.0.1:port`` that has sent ``data`` (a request, whole or in part)."""
    s = socket.create_connection(("127.0.0.1", port), timeout=5)
    s.sendall(data)
    return s


def read_until_closed(sock):
    """Every byte ``sock`` receives until the server closes the connection."""
    reply = b""
    while chunk := sock.recv(4096):
        reply += chunk
    return reply


class SlowClients:
    """``n`` connections to ``127.0.0.1:port`` that never finish their request head, in a thread.

    Non-blocking sockets under one selector: each sends ``head`` (no blank
    line) once connected and then nothing. With ``reconnect``, a connection
    the server closes (or that fails to connect) is opened again at once, so
    ``n`` connections keep pressing on the server for as long as it runs.
    ``opened`` and ``closed`` count connections; ``held`` is how many are
    connected now.
    """

    def __init__(self, port, n=300, reconnect=True, head=b"GET /healthz HTTP/1.1\r\nHost: x\r\n"):
        self.port, self.n, self.reconnect, self.head = port, int(n), reconnect, head
        self.opened = self.closed = self.held = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _open(self, sel):
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setblocking(False)
        s.connect_ex(("127.0.0.1", self.port))
        sel.register(s, selectors.EVENT_WRITE, "connecting")
        self.opened += 1

    def _drop(self, sel, s):
        if sel.get_key(s).data == "sent":
            self.held -= 1
        sel.unregister(s)
        s.close()
        self.closed += 1
        if self.reconnect and not self._stop.is_set():
            self._open(sel)

    def _run(self):
        with selectors.DefaultSelector() as sel:
            for _ in range(self.n):
                self._open(sel)
            while not self._stop.is_set():
                for key, _ in sel.select(0.05):
                    s = key.fileobj
                    try:
                        if key.data == "connecting":
                            if s.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR):
                                raise ConnectionError
                            s.send(self.head)
                            sel.modify(s, selectors.EVENT_READ, "sent")
                            self.held += 1
                        elif not s.recv(4096):
                            raise ConnectionError  # closed by the server
                    except OSError:
                        self._drop(sel, s)
            for key in list(sel.get_map().values()):
                key.fileobj.close()

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join(30)


def probe_health(url, seconds, interval=0.1, timeout=5.0):
    """``/healthz`` and ``/readyz`` in turn on a fresh connection each (as a load balancer probes) for
    ``seconds``; returns ``[(path, status or error name, seconds)]``."""
    out = []
    end = time.monotonic() + seconds
    paths = ("/healthz", "/readyz")
    while time.monotonic() < end:
        path = paths[len(out) % 2]
        t0 = time.perf_counter()
        try:
            with httpx.Client(timeout=timeout) as h:
                status = h.get(url + path).status_code
        except httpx.HTTPError as exc:
            status = type(exc).__name__
        out.append((path, status, time.perf_counter() - t0))
        time.sleep(interval)
    return out
