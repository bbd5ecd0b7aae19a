"""Shared fixtures and independent reference computations for the tests."""

import shutil
import subprocess
import tempfile
import zlib
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from bubsub.core import Mesh
from kernel_paths import warm_up_command


def convex_mesh(points, attenuation=1.0):
    """Outward-oriented convex hull of ``points`` as a Mesh."""
    hull = ConvexHull(points)
    faces = hull.simplices.copy()
    # orient each facet so that its normal points away from the interior
    centre = points[hull.vertices].mean(axis=0)
    a, b, c = (points[faces[:, i]] for i in range(3))
    flip = np.einsum("ij,ij->i", np.cross(b - a, c - a), a - centre) < 0
    faces[flip] = faces[flip][:, ::-1]
    used, inverse = np.unique(faces, return_inverse=True)
    return Mesh(points[used], inverse.reshape(-1, 3), attenuation)


def convex_chords(mesh, origins, directions):
    """Exact chord lengths of rays through a convex mesh, by half-space clipping."""
    v, f = mesh.vertices, np.asarray(mesh.faces)
    a, b, c = (v[f[:, i]] for i in range(3))
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    h = np.einsum("ij,ij->i", n, a)
    o = origins.reshape(-1, 3)
    d = directions.reshape(-1, 3)
    out = np.zeros(len(o))
    for s in range(0, len(o), 4096):
        nd = d[s:s + 4096] @ n.T
        no = o[s:s + 4096] @ n.T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (h - no) / nd
        tmin = np.where(nd < 0, t, -np.inf).max(axis=1)
        tmax = np.where(nd > 0, t, np.inf).min(axis=1)
        inside = np.all((nd != 0) | (no <= h), axis=1)
        out[s:s + 4096] = np.where(inside, np.clip(tmax - tmin, 0, None), 0.0)
    return out.reshape(origins.shape[:-1])


def sphere_chords(centre, radius, origins, directions):
    """Analytic chord lengths of rays through a sphere."""
    w = origins - np.asarray(centre)
    b = np.einsum("...i,...i", w, directions)
    c = np.einsum("...i,...i", w, w) - radius**2
    return 2.0 * np.sqrt(np.clip(b * b - c, 0.0, None))


@pytest.fixture
def rng(request):
    """A generator seeded by the test's name: reproducible, different per test."""
    return np.random.default_rng(zlib.crc32(request.node.name.encode()))


# --- tests whose work is one long subprocess ------------------------------------------------------
# A few tests spend their time in one subprocess that needs nothing from the other tests (a compile with
# bounds checks, every module imported into a fresh interpreter, a wheel served from a fresh venv, the
# example notebook's kernel). Marked ``@pytest.mark.background(command=fn)`` (a keyword: a mark called
# with one function marks that function instead), with ``fn(tmp)`` returning ``(args, env, cwd)``, their
# subprocesses run one after another, in the tests' order, from the moment the tests are collected: a
# second lane beside the tests, which leave the machine's second core idle most of the time. The lane
# moves on between tests, in pytest's own thread, so that no process is started (nor Python's garbage
# collected by another thread) while a test runs native code. The test (fixture ``background``) starts its
# own at once if the lane has not reached it, waits for it and asserts on its exit status and output as
# it would on ``subprocess.run``'s.


class BackgroundRun:
    """One subprocess, started once, its output going to files in its own temporary folder."""

    def __init__(self, command):
        self.command = command
        self.tmp = self.proc = None

    def start(self):
        """Start it unless it was (by the lane or by its test); returns the process."""
        if self.proc is None:
            self.tmp = Path(tempfile.mkdtemp(prefix="bubsub-test-bg-"))
            args, env, cwd = self.command(self.tmp)
            self._out, self._err = open(self.tmp / "stdout", "w+"), open(self.tmp / "stderr", "w+")
            self.proc = subprocess.Popen(args, env=env, cwd=cwd, stdout=self._out, stderr=self._err, text=True)
        return self.proc

    def running(self):
        return bool(self.proc) and self.proc.poll() is None

    def wait(self, timeout):
        """The finished run as a ``subprocess.CompletedProcess`` (text output)."""
        proc = self.start()
        try:
            code = proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.close()
            raise
        self._out.seek(0)
        self._err.seek(0)
        return subprocess.CompletedProcess(proc.args, code, self._out.read(), self._err.read())

    def close(self):
        if not self.proc:
            return
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self._out.close()
        self._err.close()
        shutil.rmtree(self.tmp, ignore_errors=True)


_BACKGROUND = {}

#: From this many collected tests on, the lane starts with a warm-up that compiles every kernel into
#: numba's disk cache (``kernel_paths.py``) while the first tests run; a single test's run goes without.
WARM_UP_FROM = 20


def _advance_lane():
    """Start the lane's next run unless one of the runs is still going."""
    if not any(run.running() for run in _BACKGROUND.values()):
        waiting = [run for run in _BACKGROUND.values() if run.proc is None]
        if waiting:
            waiting[0].start()


def pytest_configure(config):
    config.addinivalue_line("markers", "background(command=fn): the test's subprocess runs in a lane beside the "
                                       "other tests from their collection on (see tests/conftest.py)")


def pytest_collection_finish(session):
    if len(session.items) >= WARM_UP_FROM:
        _BACKGROUND["kernel warm-up"] = BackgroundRun(warm_up_command)
    for item in session.items:
        marker = item.get_closest_marker("background")
        if marker is not None and item.nodeid not in _BACKGROUND:
            _BACKGROUND[item.nodeid] = BackgroundRun(marker.kwargs["command"])
    _advance_lane()


def pytest_runtest_teardown(item):
    _advance_lane()


def pytest_sessionfinish(session):
    for run in _BACKGROUND.values():
        run.close()
    _BACKGROUND.clear()


@pytest.fixture
def background(request):
    """The :class:`BackgroundRun` of the test's ``background`` marker (see above)."""
    run = _BACKGROUND.get(request.node.nodeid)
    if run is None:
        run = _BACKGROUND[request.node.nodeid] = BackgroundRun(request.node.get_closest_marker("background")
                                                               .kwargs["command"])
    return run
