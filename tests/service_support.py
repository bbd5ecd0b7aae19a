"""Real servers and small phantoms for the service and client tests.

Servers are uvicorn instances in threads on free ports of 127.0.0.1. A test
module imports the fixtures it uses (``from service_support import server``);
servers are shared through :func:`shared_server`, so every module sees the
same process-wide instance, stopped at the end of the session.
"""

from __future__ import annotations

import atexit
import socket
import threading
import time
from dataclasses import dataclass

import numpy as np
import pytest
import uvicorn

from bubsub.clients.remote.client import ProjectorClient
from bubsub.core import MeshProjector, ScanGeometry, circle_surface, sphere_surface
from bubsub.service.app import create_app
from bubsub.service.config import Settings
from bubsub.service.server import uvicorn_config


def free_socket(port=0):
    """A bound TCP socket on 127.0.0.1 (proto IPPROTO_TCP, so asyncio sets TCP_NODELAY)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", port))
    return sock


class ServerThread:
    """A uvicorn server for ``create_app(settings)`` in a daemon thread.

    Parameters
    ----------
    port : int
        0 for a free port; a fixed port to restart a server where it was.
    **settings
        :class:`Settings` fields.
    """

    def __init__(self, port=0, **settings):
        # blas_threads=None: an in-process server must not change the test process's BLAS pools
        self.settings = Settings(**{"workers": 2, "blas_threads": None, **settings})
        self.sock = free_socket(port)
        self.port = self.sock.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self.app = create_app(self.settings)
        config = uvicorn_config(self.app, self.settings, log_level="warning", timeout_graceful_shutdown=10)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)
        self.thread.start()
        end = time.monotonic() + 60  # the machine may be busy
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() > end:
                raise RuntimeError("test server did not start")
            time.sleep(0.01)

    @property
    def state(self):
        return self.app.state.service

    def stop(self):
        """Stop serving (in-flight requests finish) and wait for the thread."""
        if self.thread.is_alive():
            self.server.should_exit = True
            self.thread.join(30)
        self.sock.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


_SHARED = {}
_LOCK = threading.Lock()


def shared_server(name, **settings):
    """The process-wide server ``name``, started on first use."""
    with _LOCK:
        if name not in _SHARED:
            _SHARED[name] = ServerThread(**settings)
        return _SHARED[name]


def stop_shared():
    """Stop every shared server."""
    with _LOCK:
        for s in list(_SHARED.values()):
            s.stop()
        _SHARED.clear()


atexit.register(stop_shared)


@pytest.fixture(scope="session")
def server():
    """The default test server (no auth, 4 MiB bodies, ample queue)."""
    yield shared_server("default", max_body_bytes=4 << 20, max_queue=64)
    stop_shared()


@pytest.fixture
def client(server):
    with ProjectorClient(server.url, retry_timeout=30) as c:
        yield c


# -- phantoms ------------------------------------------------------------------------------

@dataclass
class Phantom:
    geometry: ScanGeometry
    truth: list
    init: list
    data: np.ndarray
    projector: MeshProjector


def phantom_2d(shift=0.0, n_angles=24, cols=96, bubbles=((-6.0, 0.0, 4.0), (6.0, 3.0, 3.0), (0.0, -7.0, 3.5))):
    """Three circular bubbles in a 2D parallel scan, and a perturbed start."""
    g = ScanGeometry.parallel(np.linspace(0, np.pi, n_angles, endpoint=False), pixel_size=0.3, cols=cols)
    truth = [circle_surface((x + shift, y), r, 1.0) for x, y, r in bubbles]
    init = [circle_surface((x + shift + 0.5, y - 0.5), 0.85 * r, 1.0) for x, y, r in bubbles]
    p = MeshProjector(g)
    return Phantom(g, truth, init, p.forward(truth), p)


def phantom_3d(n_angles=12, det=40):
    """Two spherical bubbles in a 3D cone-beam scan, and a perturbed start."""
    g = ScanGeometry.cone(np.linspace(0, 2 * np.pi, n_angles, endpoint=False), source_origin=150.0,
                          origin_detector=50.0, pixel_size=0.6, cols=det, rows=det)
    truth = [sphere_surface((-3.0, 0.0, 1.0), 4.0, 1.0, control=12), sphere_surface((4.0, 2.0, -1.0), 3.0, 1.0, control=12)]
    init = [sphere_surface((-2.5, 0.5, 1.0), 3.5, 1.0, control=12), sphere_surface((3.5, 2.0, -0.5), 3.3, 1.0, control=12)]
    p = MeshProjector(g)
    return Phantom(g, truth, init, p.forward(truth), p)


@pytest.fixture(scope="session")
def p2d():
    return phantom_2d()


@pytest.fixture(scope="session")
def p3d():
    return phantom_3d()
