"""Client of the bubsub projection server: a remote drop-in for :class:`~bubsub.core.MeshProjector`.

>>> with ProjectorClient("http://127.0.0.1:8000") as client:      # doctest: +SKIP
...     job = client.create_job(geometry, data=sino, surfaces=surfaces)
...     f, grads = job.objective(surfaces)          # same as MeshProjector(geometry).objective(surfaces, sino)
...     result = fit(job, surfaces)                 # bubsub.clients.optimise.fit runs locally, projects remotely

A :class:`RemoteJob` keeps everything it was created from (geometry, data,
background, surface topology, initial control vertices), so when the server
restarts or expires the job, the next call re-creates it and repeats itself:
a fit survives a server restart and continues from its last iterate.

Only ``httpx`` and ``numpy`` are needed (the ``client`` extra).

It is one module on purpose: :class:`ProjectorClient` and :class:`RemoteJob` share the connection, its
retries and the re-creation of an expired job, which only make sense together.
"""

from __future__ import annotations

import io
import json
import logging
import random
import socket
import threading
import time

import httpx
import numpy as np

from bubsub.core import SubdivisionSurface

__all__ = ["ProjectorClient", "RemoteJob", "RemoteError", "RemoteValueError", "UnknownJobError", "connect"]

log = logging.getLogger("bubsub.client")

NPY = "application/x-npy"
NPZ = "application/x-npz"

_RETRY_STATUS = {502, 503, 504}
#: error codes of those statuses that a retry would only repeat (the server stopped the computation at its timeout)
_FINAL_CODES = {"compute_timeout"}
_RETRY_ERRORS = (httpx.ConnectError, httpx.ConnectTimeout, httpx.ReadError, httpx.WriteError,
                 httpx.RemoteProtocolError, httpx.PoolTimeout)


class RemoteError(RuntimeError):
    """The server answered an error.

    Attributes
    ----------
    status : int
        HTTP status (0 when the server could not be reached).
    code : str
        Machine-readable code from the JSON body (``unknown_job``, ``busy`` ...).
    detail : str
        The server's message.
    """

    def __init__(self, status, code, detail):
        super().__init__(f"{status} {code}: {detail}" if status else detail)
        self.status, self.code, self.detail = status, code, detail


class RemoteValueError(RemoteError, ValueError):
    """A 4xx answer about the request's content (bad shape, dtype, NaN ...): a ``ValueError``, as locally."""


class UnknownJobError(RemoteError):
    """The job does not exist on the server (never created, expired, deleted, or server restarted)."""


def _npy(array):
    buf = io.BytesIO()
    np.save(buf, np.asarray(array), allow_pickle=False)
    return buf.getvalue()


def _npz(**arrays):
    buf = io.BytesIO()
    np.savez(buf, **{k: np.asarray(v) for k, v in arrays.items()})
    return buf.getvalue()


def _load_npy(content):
    return np.load(io.BytesIO(content), allow_pickle=False)


def _error(response):
    try:
        body = response.json()
        code, detail = str(body.get("code", "error")), body.get("detail", response.text)
    except ValueError:
        code, detail = "error", response.text[:500] or response.reason_phrase
    if not isinstance(detail, str):
        detail = json.dumps(detail)
    status = response.status_code
    if status == 404 and code == "unknown_job":
        return UnknownJobError(status, code, detail)
    if status in (400, 409, 413, 415, 422):
        return RemoteValueError(status, code, detail)
    return RemoteError(status, code, detail)


def _geometry_json(geometry):
    return {
        "kind": geometry.kind,
        "vectors": np.asarray(geometry.vectors, dtype=float).tolist(),
        "det_rows": geometry.det_rows,
        "det_cols": geometry.det_cols,
    }


def _topology(surfaces):
    """Surface groups (JSON) of consecutive surfaces with equal topology, levels and attenuation."""
    groups = []
    last = None
    for s in surfaces:
        faces = s.control_faces if getattr(s, "ndim", 2) == 3 else None
        key = (len(s.vertices), s.levels, float(s.attenuation), None if faces is None else faces.shape)
        if last is not None and last[0] == key and (faces is None or np.array_equal(last[1], faces)):
            groups[-1]["count"] += 1
            continue
        groups.append({
            "n_control": len(s.vertices),
            "faces": None if faces is None else np.asarray(faces, dtype=np.int64).tolist(),
            "levels": int(s.levels),
            "attenuation": float(s.attenuation),
            "count": 1,
        })
        last = (key, faces)
    return groups


class ProjectorClient:
    """HTTP client of a bubsub projection server.

    Parameters
    ----------
    base_url : str
        E.g. ``http://127.0.0.1:8000``.
    token : str, optional
        Bearer token (servers with ``BUBSUB_TOKENS``).
    timeout : float or None
        Seconds per HTTP request (None: wait forever).
    retry_timeout : float
        How long to keep retrying a request on 502/503/504 and connection
        errors (exponential backoff from ``backoff`` to ``max_backoff``
        seconds, honouring ``Retry-After``).
    backoff, max_backoff : float
    transport : httpx.BaseTransport, optional
        For tests.

    Notes
    -----
    Use it as a context manager (or call :meth:`close`) to release its
    connections. One client can be shared by several threads.
    """

    def __init__(self, base_url, token=None, timeout=120.0, *, retry_timeout=120.0, backoff=0.05,
                 max_backoff=5.0, transport=None):
        headers = {"User-Agent": "bubsub-client/1"}
        if token:
            headers["Authorization"] = f"Bearer {token}"
        self.base_url = str(base_url).rstrip("/")
        self.retry_timeout = float(retry_timeout)
        self.backoff = float(backoff)
        self.max_backoff = float(max_backoff)
        limits = httpx.Limits(max_connections=64, max_keepalive_connections=16)
        if transport is None:
            # TCP_NODELAY: httpx writes headers and body separately; with Nagle's algorithm the body
            # would wait for the server's delayed ACK (~40 ms per request).
            transport = httpx.HTTPTransport(limits=limits,
                                            socket_options=[(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)])
        self._http = httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout, transport=transport,
                                  limits=limits)

    # -- plumbing ---------------------------------------------------------------------
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        """Close the connections."""
        self._http.close()

    def __repr__(self):
        return f"ProjectorClient({self.base_url!r})"

    def request(self, method, path, *, ok=(200,), **kwargs):
        """Send a request, retrying on 502/503/504 and connection errors.

        Parameters
        ----------
        method, path : str
        ok : tuple of int
            Statuses that count as success.
        **kwargs
            Passed to :meth:`httpx.Client.request`.

        Returns
        -------
        httpx.Response

        Raises
        ------
        RemoteError
            For an error answer (:class:`UnknownJobError` for an unknown job,
            :class:`RemoteValueError` for a bad request), or when retrying
            gave up (``status`` is then the last status, or 0).
        """
        deadline = time.monotonic() + self.retry_timeout
        delay = self.backoff
        attempt = 0
        while True:
            attempt += 1
            try:
                response = self._http.request(method, path, **kwargs)
            except _RETRY_ERRORS as exc:
                if time.monotonic() + delay > deadline:
                    raise RemoteError(0, "unreachable", f"{method} {path}: {type(exc).__name__}: {exc} "
                                                       f"(gave up after {attempt} attempts)") from exc
                log.info("%s %s: %s; retrying in %.2f s", method, path, type(exc).__name__, delay)
                wait = delay
            else:
                if response.status_code in ok:
                    return response
                if response.status_code not in _RETRY_STATUS or _error(response).code in _FINAL_CODES:
                    raise _error(response)
                wait = max(delay, _retry_after(response))
                if time.monotonic() + wait > deadline:
                    raise _error(response)
                log.info("%s %s: %d; retrying in %.2f s", method, path, response.status_code, wait)
            time.sleep(wait * (0.75 + 0.5 * random.random()))
            delay = min(delay * 2.0, self.max_backoff)

    # -- server ---------------------------------------------------------------------
    def healthy(self):
        """Whether ``/healthz`` answers 200 (no retries)."""
        try:
            return self._http.get("/healthz").status_code == 200
        except httpx.HTTPError:
            return False

    def ready(self):
        """Whether ``/readyz`` answers 200 (no retries)."""
        try:
            return self._http.get("/readyz").status_code == 200
        except httpx.HTTPError:
            return False

    def wait_ready(self, timeout=30.0, interval=0.1):
        """Block until the server is ready; ``TimeoutError`` after ``timeout`` seconds."""
        end = time.monotonic() + timeout
        while not self.ready():
            if time.monotonic() > end:
                raise TimeoutError(f"{self.base_url} not ready after {timeout} s")
            time.sleep(interval)
        return self

    def jobs(self):
        """Descriptions (dicts) of this token's jobs on the server."""
        return self.request("GET", "/v1/jobs").json()["jobs"]

    # -- jobs -----------------------------------------------------------------------
    def create_job(self, geometry, data=None, background=None, surfaces=(), supersampling=1):
        """Create a job on the server.

        Parameters
        ----------
        geometry : ScanGeometry
        data : array of ``geometry.shape``, optional
            Measured projections (the objective's default target).
        background : array of ``geometry.shape``, optional
            Stationary background, subtracted from ``data`` on the server.
        surfaces : sequence of SubdivisionSurface
            The surfaces to fit: their topology (control faces in 3D, control
            point count in 2D), levels and attenuation define the job; their
            control vertices are sent once to validate the control meshes.
        supersampling : int

        Returns
        -------
        RemoteJob
        """
        surfaces = _as_list(surfaces)
        if not surfaces:
            raise ValueError("create_job needs the surfaces to fit (SubdivisionSurface objects)")
        job = RemoteJob(self, geometry, surfaces, data, background, supersampling)
        job._create()
        return job


def _retry_after(response):
    try:
        return max(0.0, float(response.headers.get("retry-after", 0)))
    except ValueError:
        return 0.0


def _as_list(items):
    items = [items] if isinstance(items, SubdivisionSurface) else list(items)
    for k, item in enumerate(items):
        if not isinstance(item, SubdivisionSurface):
            raise TypeError(f"item {k} is a {type(item).__name__}; a remote job projects SubdivisionSurface "
                            f"objects (the server subdivides their control vertices)")
    return items


class RemoteJob:
    """A job on a projection server, with the methods of :class:`~bubsub.core.MeshProjector`.

    Made by :meth:`ProjectorClient.create_job`. ``forward``, ``vjp`` and
    ``objective`` take SubdivisionSurface items with the job's topology (only
    their control vertices are sent) and return what the local projector
    returns, to float32 round-off. ``objective(items)`` without ``data`` fits
    the job's data minus its background.

    Attributes
    ----------
    job_id : str or None
        The server's job id (changes when the job is re-created; None once
        deleted). ``id`` is the same.
    geometry : ScanGeometry
    supersampling : int
    recreated : int
        How often the job was re-created after the server lost it.
    server : str
        The server's URL.
    """

    def __init__(self, client, geometry, surfaces, data, background, supersampling):
        self.client = client
        self.geometry = geometry
        self.supersampling = int(supersampling)
        self._meta = json.dumps({
            "geometry": _geometry_json(geometry),
            "surfaces": _topology(surfaces),
            "supersampling": self.supersampling,
        }).encode()
        self._shapes = [np.shape(s.vertices) for s in surfaces]
        self._check = [(int(s.levels), float(s.attenuation)) for s in surfaces]
        self._vertices = np.concatenate([np.asarray(s.vertices, dtype=np.float64) for s in surfaces])
        self._data = None if data is None else np.asarray(data, dtype=np.float32)
        self._background = None if background is None else np.asarray(background, dtype=np.float32)
        self.job_id = None
        self.recreated = 0
        self._lock = threading.Lock()

    # -- protocol -----------------------------------------------------------------
    @property
    def id(self):
        """The server's job id (alias of ``job_id``)."""
        return self.job_id

    @property
    def range_shape(self):
        """Shape of the projections, ``geometry.shape``."""
        return self.geometry.shape

    @property
    def server(self):
        """The server's URL (where this projector runs, for reports)."""
        return self.client.base_url

    def __repr__(self):
        return f"RemoteJob({self.id!r} on {self.client.base_url}, {len(self._shapes)} surfaces)"

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.delete()

    def _create(self):
        files = {"job": (None, self._meta, "application/json"),
                 "vertices": ("vertices.npy", _npy(self._vertices), NPY)}
        if self._data is not None:
            files["data"] = ("data.npy", _npy(self._data), NPY)
        if self._background is not None:
            files["background"] = ("background.npy", _npy(self._background), NPY)
        info = self.client.request("POST", "/v1/jobs", ok=(201,), files=files).json()
        self.job_id = info["id"]
        return info

    def _call(self, method, suffix, **kwargs):
        """Request on this job; re-create it once if the server no longer knows it."""
        job_id = self.job_id
        try:
            return self.client.request(method, f"/v1/jobs/{job_id}{suffix}", **kwargs)
        except UnknownJobError:
            with self._lock:  # threads sharing this job re-create it once
                if self.job_id == job_id:
                    log.warning("job %s unknown to the server (restart or expiry); re-creating it", job_id)
                    self._create()
                    self.recreated += 1
            return self.client.request(method, f"/v1/jobs/{self.job_id}{suffix}", **kwargs)

    def _stack(self, items):
        items = _as_list(items)
        if len(items) != len(self._shapes):
            raise ValueError(f"the job fits {len(self._shapes)} surfaces, got {len(items)} items")
        out = []
        for k, (item, shape, (levels, mu)) in enumerate(zip(items, self._shapes, self._check)):
            v = np.asarray(item.vertices, dtype=np.float64)
            if v.shape != shape:
                raise ValueError(f"item {k}: control vertices must have shape {shape} (the job's topology), "
                                 f"got {v.shape}")
            if getattr(item, "levels", levels) != levels or float(getattr(item, "attenuation", mu)) != mu:
                raise ValueError(f"item {k}: levels/attenuation differ from the job's ({levels}, {mu}); "
                                 f"create a new job for a new topology")
            out.append(v)
        return np.concatenate(out)

    def _split(self, stacked):
        out, pos = [], 0
        for shape in self._shapes:
            out.append(stacked[pos:pos + shape[0]])
            pos += shape[0]
        return out

    # -- MeshProjector methods ----------------------------------------------------------
    def forward(self, items):
        """Projections of the surfaces: float32 array of ``geometry.shape``."""
        body = _npy(self._stack(items))
        r = self._call("POST", "/forward", content=body, headers={"Content-Type": NPY})
        return _load_npy(r.content)

    def vjp(self, items, residual):
        """Gradient of ``<forward(items), residual>`` w.r.t. each item's control vertices.

        Returns
        -------
        list of (n_i, d) float64
        """
        r = np.asarray(residual)
        if r.shape != tuple(self.geometry.shape):
            raise ValueError(f"residual must have shape {self.geometry.shape} (geometry.shape), got {r.shape}")
        body = _npz(vertices=self._stack(items), residual=r)
        resp = self._call("POST", "/vjp", content=body, headers={"Content-Type": NPZ})
        return self._split(_load_npy(resp.content))

    def objective(self, items, data=None):
        """``0.5 ||forward(items) - target||^2`` and its gradient w.r.t. the control vertices.

        Parameters
        ----------
        items : sequence of SubdivisionSurface
        data : array of ``geometry.shape``, optional
            Target; default: the job's data minus its background.

        Returns
        -------
        f : float
        grads : list of (n_i, d) float64
        """
        x = self._stack(items)
        if data is None:
            body, ctype = _npy(x), NPY
        else:
            d = np.asarray(data)
            if d.shape != tuple(self.geometry.shape):
                raise ValueError(f"data must have shape {self.geometry.shape} (geometry.shape), got {d.shape}")
            body, ctype = _npz(vertices=x, data=d), NPZ
        resp = self._call("POST", "/objective", content=body, headers={"Content-Type": ctype})
        with np.load(io.BytesIO(resp.content), allow_pickle=False) as z:
            return float(z["value"]), self._split(z["gradient"])

    # -- job management -------------------------------------------------------------
    def info(self):
        """The server's description of the job (dict)."""
        return self._call("GET", "").json()

    def set_data(self, data):
        """Replace the job's data (kept client-side too, for re-creation)."""
        self._data = None if data is None else np.asarray(data, dtype=np.float32)
        self._put("data", self._data)

    def set_background(self, background):
        """Replace the job's stationary background."""
        self._background = None if background is None else np.asarray(background, dtype=np.float32)
        self._put("background", self._background)

    def _put(self, which, array):
        if array is None:
            self._call("DELETE", f"/{which}")
        else:
            self._call("PUT", f"/{which}", content=_npy(array), headers={"Content-Type": NPY})

    def delete(self):
        """Delete the job on the server (no error if it is already gone)."""
        if self.job_id is None:
            return
        try:
            self.client.request("DELETE", f"/v1/jobs/{self.job_id}", ok=(204,))
        except UnknownJobError:
            pass
        self.job_id = None


def connect(url, token=None):
    """A :class:`ProjectorClient` for ``url``, checked to answer within seconds.

    Raises
    ------
    ValueError
        One line naming the URL when the server does not answer ``/healthz``
        or refuses the token.
    """
    # connection attempts give up after 10 s, so an unreachable host fails in seconds, not minutes
    client = ProjectorClient(url, token=token, timeout=httpx.Timeout(120.0, connect=10.0), retry_timeout=60.0)
    if not client.healthy():
        client.close()
        raise ValueError(f"no projector server answers at {url} (GET {url.rstrip('/')}/healthz failed); "
                         f"start one with `bubsub serve` or correct --server")
    try:
        client.jobs()  # an authenticated request: a wrong --token fails now, not after the preview
    except RemoteError as exc:
        client.close()
        raise ValueError(f"the projector server at {url} refused the request: {exc}") from None
    return client
