"""Memory budget of computations, checked before they run.

What a job *stores* is capped by the job store; what one request *computes*
can be far larger (a huge detector with no data, thousands of finely
subdivided surfaces). :func:`estimate` gives the bytes a
``forward``/``vjp``/``objective`` call on a job allocates at its peak, from
the job's shape, the request's vertices and arrays, and the projector's
backend and threads; a request over the per-job cap is refused with 413
before it runs, and :class:`ComputeBudget` keeps the running calls together
within ``BUBSUB_MAX_COMPUTE_BYTES`` (507 for a request larger than all of it,
503 while the running ones leave too little).

The model follows what the projector allocates, phase by phase (the peak is
the largest phase, plus what lives through all of them):

* throughout: the request's body and decoded arrays (and the float32 copies
  the job checks them into), and the scene: fine vertices and faces and the
  per-face arrays of the backend (per thread: projected vertices, candidate
  lists; raster: one bit per face and view);
* tracing: the float64 sums (8 bytes a pixel) and, per thread, the raster
  backend's sub-ray lattice of one view (8 bytes a lattice point) or a ray
  caster's chunk of rays; the crossings kept for the gradient (raster: 32
  bytes each, vjp/objective only, at most its store of
  ``BUBSUB_RASTER_STORE_MB``; ray casters: 28 bytes each, always, and the
  candidate pixel lists);
* forward's result: the average with supersampling (8 bytes a pixel), the
  float32 projection (4) and its ``.npy`` encoding (4, grown in steps);
* gradient: the per-pixel weights (8 bytes a pixel for vjp, and for objective
  with supersampling) and the per-face sums of each thread or ray chunk.

Crossings are counted from the request's control vertices: each surface's
bounding sphere (Loop and four-point subdivision keep a surface inside its
control vertices' hull) is projected per view, and a sub-ray that passes
through its disc is assumed to cross it ``BUBSUB_CROSSINGS_PER_RAY`` times
(2: convex bubbles). ``python -m bubsub.bench admission`` prints the estimate
against the server's measured peak per job shape;
``tests/test_service_budget.py`` checks both bounds.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from bubsub.core.projection.backends.frames import RAY_CHUNK  # rays per work item of the ray casters
from bubsub.service.errors import APIError
from bubsub.core.projection.backends.raster import ITEM_MAJOR_FACES, store_bytes

__all__ = ["Estimate", "estimate", "check_job", "ComputeBudget", "OVERHEAD_BYTES", "PIXEL_BYTES", "BackendCosts", "RASTER",
           "RAY_CASTER"]

#: per output pixel, by phase: the float64 sums; the float32 projection; the average of supersampled sums
#: (also the vjp's and a supersampled objective's per-pixel weights); the .npy encoding of the float32
#: projection (BytesIO grows in steps: about 1.4 times the array at its peak)
PIXEL_BYTES = {"sums": 8, "float32": 4, "average": 8, "encoding": 6}


@dataclass(frozen=True)
class BackendCosts:
    """Bytes a backend allocates per item of a computation (see the module docstring).

    Attributes
    ----------
    vertex, face : dict
        Per fine vertex / face (segment in 2D), by ``ndim``: the scene's arrays.
    vertex_thread : int
        Per fine vertex and worker thread (projected vertices).
    face_thread : dict
        Per face and worker thread (raster) or ray chunk (ray casters), by ``ndim``: the gradient's face sums.
    face_view : float
        Per face and view (the raster backend's bit per face found crossed).
    pixel : int
        Per pixel while tracing, besides the sums (ray casters: how far each pixel's rays go).
    lattice_point : int
        Per sub-ray lattice point of one view and thread (raster).
    chunk : int
        Per worker thread: one chunk of rays (ray casters).
    crossing : int
        Per crossing kept (raster: for the gradient only, within its store).
    ray : int
        Per pixel whose rays may meet a surface (ray casters' candidate lists).
    """

    vertex: dict
    face: dict
    vertex_thread: int
    face_thread: dict
    face_view: float
    pixel: int
    lattice_point: int
    chunk: int
    crossing: int
    ray: int


#: the raster backend: measured (python -m bubsub.bench admission) and counted from its arrays
RASTER = BackendCosts(vertex={2: 100, 3: 48}, face={2: 50, 3: 60}, vertex_thread=24, face_thread={2: 16, 3: 24},
                      face_view=1 / 8, pixel=0, lattice_point=8, chunk=0, crossing=32, ray=0)
#: the Embree ray casters (native, embreex): scene, BVH and per-chunk ray arrays
RAY_CASTER = BackendCosts(vertex={2: 250, 3: 70}, face={2: 200, 3: 110}, vertex_thread=0,
                          face_thread={2: 24, 3: 24}, face_view=0, pixel=8, lattice_point=0, chunk=RAY_CHUNK * 20,
                          crossing=28, ray=16)

#: transparent huge page (numpy asks for them on large arrays): each part of the raster store is touched
#: from its start, and its first and last pages are resident whole (half a page more than it holds, on
#: average)
HUGE_PAGE = 2 << 20

#: what a call may use beyond the estimate: the interpreter's own allocations, kernels loaded on a
#: first call, fragmentation
OVERHEAD_BYTES = 64 << 20


@dataclass(frozen=True)
class Estimate:
    """Estimated memory of one computation, by part (bytes unless said otherwise).

    Attributes
    ----------
    op : str
    backend : str
    pixels : int
        Output pixels.
    inputs : int
        The request's body, decoded arrays and their checked copies.
    scene : int
        Fine meshes and per-face arrays, all threads.
    trace : int
        Tracing: sums, lattices or ray chunks, candidate lists.
    kept : int
        Crossings kept for the gradient (ray casters: also by forward).
    result : int
        Forward: average, float32 projection and encoding. Gradient: weights and face sums.
    crossings : int
        Crossings assumed (a count).
    fine_vertices : int
        A count.
    """

    op: str
    backend: str
    pixels: int
    inputs: int
    scene: int
    trace: int
    kept: int
    result: int
    crossings: int
    fine_vertices: int

    @property
    def total(self):
        return self.inputs + self.scene + self.kept + max(self.trace, self.result)

    def describe(self):
        """The parts in words, for error messages."""
        return (f"{self.pixels} output pixels, {self.fine_vertices} fine vertices, {self.crossings} crossings "
                f"assumed; {self.inputs} bytes of request arrays, {self.scene} of scene, {self.trace} to trace, "
                f"{self.kept} of crossings kept, {self.result} for the result ({self.backend} backend)")


def _fine_counts(group):
    """Fine vertices and faces (segments in 2D) of one surface of ``group`` (exact once built, else Loop's)."""
    if group.template is not None:
        n = int(group.template.S.shape[0])
        faces = group.template._topo.fine_faces  # noqa: SLF001 - size accounting only
        return n, (n if faces is None else len(faces))
    if group.faces is None:
        n = group.n_control << group.levels
        return n, n
    m = len(group.faces) * 4 ** group.levels
    return m // 2 + 2, m


def _bounding_spheres(job, x):
    """Centre and radius of a sphere around each surface's control vertices (3D coordinates).

    Loop and four-point subdivision make convex combinations of control
    vertices, so each fine surface lies inside its control vertices' sphere.
    """
    centres, radii = [], []
    pos = 0
    for g in job.groups:
        v = x[pos:pos + g.count * g.n_control].reshape(g.count, g.n_control, job.ndim)
        pos += g.count * g.n_control
        c = (v.min(axis=1) + v.max(axis=1)) / 2
        centres.append(c)
        radii.append(np.sqrt(((v - c[:, None, :]) ** 2).sum(axis=2).max(axis=1)) * 1.001 + 1e-9)
    c = np.concatenate(centres)
    if job.ndim == 2:
        c = np.concatenate([c, np.zeros((len(c), 1))], axis=1)
    return c, np.concatenate(radii)


def _footprints(job, x):
    """``(pixels that may see a surface, sum over surfaces of the pixels inside its projected disc)``.

    The same bound as the core projector's ray culling (each surface's sphere
    enclosed in a detector-aligned cube, its projected corners bounding the
    pixels it can shadow, with a pixel's margin) for the first count, at most
    the pixels; the second counts a pixel once per surface whose projected
    sphere covers it: a quarter circle's share of the corners' box without the
    margin (the whole extent in 2D), clipped to the detector.
    """
    f = job.projector._frames  # noqa: SLF001 - the projector's own detector frames
    centre, radius = _bounding_spheres(job, x)
    signs = np.array([[(i >> j) & 1 for j in range(3)] for i in range(8)], float) * 2 - 1
    per_view = f.rows * f.cols
    union = total = 0.0
    for p in range(f.n):
        d, u, v = f.d[p], f.u[p], f.v[p]
        nrm = np.cross(u, v)
        axes = np.stack([u / np.linalg.norm(u), v / np.linalg.norm(v), nrm / np.linalg.norm(nrm)])
        X = (centre[:, None, :] + radius[:, None, None] * (signs @ axes)).reshape(-1, 3)
        if f.cone:
            s = f.s[p]
            den = (X - s) @ nrm
            with np.errstate(divide="ignore", invalid="ignore"):
                lam = ((d - s) @ nrm) / den
            if not np.all(np.isfinite(lam) & (lam > 0)):
                union += per_view  # a sphere around or behind the source: every ray is cast
                total += per_view * len(radius)
                continue
            P = s + lam[:, None] * (X - s)
        else:
            ray = f.s[p]
            den = ray @ nrm
            if den == 0:
                union += per_view
                total += per_view * len(radius)
                continue
            P = X + (((d - X) @ nrm) / den)[:, None] * ray
        rel = P - d
        a = (rel @ np.cross(v, nrm) / (u @ np.cross(v, nrm))).reshape(-1, 8) + f.cols / 2
        cols_box = np.clip(np.ceil(a.max(1)) + 1, 0, f.cols) - np.clip(np.floor(a.min(1)) - 1, 0, f.cols)
        cols_disc = np.clip(a.max(1), 0, f.cols) - np.clip(a.min(1), 0, f.cols)
        if f.ndim == 3:
            b = (rel @ np.cross(nrm, u) / (v @ np.cross(nrm, u))).reshape(-1, 8) + f.rows / 2
            rows_box = np.clip(np.ceil(b.max(1)) + 1, 0, f.rows) - np.clip(np.floor(b.min(1)) - 1, 0, f.rows)
            disc = np.pi / 4 * cols_disc * (np.clip(b.max(1), 0, f.rows) - np.clip(b.min(1), 0, f.rows))
        else:
            rows_box, disc = 1, cols_disc
        union += min(per_view, float(np.sum(cols_box * rows_box)))
        total += float(np.sum(disc))
    return int(union), int(np.ceil(total))


def _store_cap(job):
    """Bytes the raster backend may keep for a gradient (its store, split evenly among the views)."""
    n = job.geometry.n_angles
    pixels = int(np.prod(job.geometry.shape))
    return (store_bytes() // 32 // n) * n * 32 if job.ndim == 3 and pixels < 2 ** 31 else 0


def estimate(job, op, crossings_per_ray, vertices=None, arrays=None, body_bytes=0):
    """Estimated peak memory of ``op`` on ``job`` (see the module docstring).

    Parameters
    ----------
    job : Job
    op : {"forward", "vjp", "objective"}
    crossings_per_ray : int
        Crossings a sub-ray is assumed to have with one surface it meets
        (``BUBSUB_CROSSINGS_PER_RAY``; 2 for convex bubbles).
    vertices : (n_control_total, ndim) float, optional
        Checked control vertices of the request: crossings and rays are those
        of the pixels that may see a surface. Without them only the parts that
        do not depend on the vertices are counted (as when a job is created).
    arrays : dict of numpy.ndarray, optional
        The request's decoded arrays (vertices, residual, data): each, and a
        float32 copy of each projection-shaped one, live through the call.
    body_bytes : int
        Size of the request body, held until the response is sent.

    Returns
    -------
    Estimate
    """
    backend = job.projector.backend
    costs = RASTER if backend == "raster" else RAY_CASTER
    shape = job.geometry.shape
    pixels = int(np.prod(shape))
    views = job.geometry.n_angles
    k2 = job.supersampling ** 2 if job.ndim == 3 else job.supersampling
    threads = max(1, min(job.projector.threads, views))
    gradient = op != "forward"

    counts = [(g.count, *_fine_counts(g)) for g in job.groups]
    n_vertices = sum(c * v for c, v, _ in counts)
    n_faces = sum(c * f for c, _, f in counts)
    scene = (n_vertices * (costs.vertex[job.ndim] + costs.vertex_thread * threads)
             + n_faces * costs.face[job.ndim] + int(n_faces * views * costs.face_view))

    inputs = int(body_bytes)
    for name, a in (arrays or {}).items():
        inputs += int(a.nbytes)
        if tuple(a.shape) == tuple(shape):
            inputs += PIXEL_BYTES["float32"] * pixels  # Job.check_projection's float32 copy
    rays, crossings = (0, 0) if vertices is None else _footprints(job, vertices)
    crossings *= k2 * int(crossings_per_ray)

    sums = PIXEL_BYTES["sums"] * pixels
    lattice = threads * (pixels // views) * k2 * costs.lattice_point
    trace = sums + costs.pixel * pixels + lattice + threads * costs.chunk + costs.ray * rays
    kept = costs.crossing * crossings
    # raster: an array of face sums per thread; ray casters: one per chunk of rays, all kept until summed
    parts = threads if backend == "raster" else max(1, -(-rays * k2 // RAY_CHUNK))
    face_sums = costs.face_thread[job.ndim] * n_faces * parts
    if backend == "raster":
        cap = _store_cap(job)
        if kept <= cap and job.ndim == 3 and k2 == 1 and n_faces >= ITEM_MAJOR_FACES:
            face_sums //= threads  # kept item by item: one array of face sums for all threads
        # three arrays (face, pixel, coefficients) per thread
        kept = min(kept + 3 * threads * HUGE_PAGE // 2, cap) if gradient and kept > 0 else 0
    if gradient:
        weights = PIXEL_BYTES["average"] * pixels if op == "vjp" or k2 > 1 else 0
        result = sums + weights + lattice + face_sums + 24 * n_vertices
    else:
        result = max(sums + PIXEL_BYTES["average"] * pixels * (k2 > 1) + PIXEL_BYTES["float32"] * pixels,
                     (PIXEL_BYTES["float32"] + PIXEL_BYTES["encoding"]) * pixels)
    return Estimate(op, backend, pixels, inputs, scene, trace, kept, result, crossings, n_vertices)


def check_job(need, cap):
    """413 when one call of ``need`` (an :class:`Estimate`) exceeds the per-job compute cap ``cap``."""
    total = need.total
    if total > cap:
        raise APIError(413, f"{need.op} on this job needs an estimated {total} bytes ({need.describe()}), "
                            f"over the per-job cap of {cap} bytes (BUBSUB_JOB_COMPUTE_MAX_BYTES, default "
                            f"BUBSUB_JOB_MAX_BYTES) by {total - cap} bytes; use fewer pixels, less supersampling, fewer "
                            f"levels or fewer surfaces per job", "compute_too_large")


class ComputeBudget:
    """Bytes reserved by running computations, within ``limit``.

    Parameters
    ----------
    limit : int
        ``BUBSUB_MAX_COMPUTE_BYTES``.
    retry_after : int
        ``Retry-After`` seconds of a 503.
    """

    def __init__(self, limit, retry_after=1):
        self.limit = int(limit)
        self.retry_after = int(retry_after)
        self.reserved = 0
        self._lock = threading.Lock()

    def reserve(self, nbytes):
        """Reserve ``nbytes``; 507 if it exceeds the whole budget, 503 if running calls leave too little."""
        nbytes = int(nbytes)
        if nbytes > self.limit:
            raise APIError(507, f"this computation needs an estimated {nbytes} bytes, over the server's compute "
                                f"budget of {self.limit} bytes (BUBSUB_MAX_COMPUTE_BYTES) by "
                                f"{nbytes - self.limit} bytes", "compute_too_large")
        with self._lock:
            if self.reserved + nbytes > self.limit:
                free = self.limit - self.reserved
                raise APIError(503, f"this computation needs an estimated {nbytes} bytes; running ones leave "
                                    f"{free} of the {self.limit}-byte compute budget (BUBSUB_MAX_COMPUTE_BYTES), "
                                    f"{nbytes - free} bytes short; retry after {self.retry_after} s",
                               "compute_busy", {"Retry-After": str(self.retry_after)})
            self.reserved += nbytes

    def release(self, nbytes):
        with self._lock:
            self.reserved -= int(nbytes)
