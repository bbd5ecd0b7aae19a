"""Memory budget of computations, checked before they run.

What a job *stores* is capped by the job store; what one request *computes*
can be far larger (a huge detector with no data, thousands of finely
subdivided surfaces). :func:`estimate` gives an upper estimate of the bytes a
``forward``/``vjp``/``objective`` call on a job allocates, from the job's
shape alone; a request over the per-job cap is refused with 413 before it
runs, and :class:`ComputeBudget` keeps the running calls together within
``BUBSUB_MAX_COMPUTE_BYTES`` (507 for a request larger than all of it, 503
while the running ones leave too little).

The byte counts per pixel, sub-ray, crossing and fine vertex were measured
on the core projector (peak RSS of one call; ``tests/test_service_budget.py``
checks the server's real peak against the estimate).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from .errors import APIError

__all__ = ["Estimate", "estimate", "check_job", "ComputeBudget", "PIXEL_BYTES", "RAY_BYTES", "CROSSING_BYTES",
           "FINE_VERTEX_BYTES", "OVERHEAD_BYTES"]

#: per output pixel: float64 accumulator, float32 projection and its encoding (x 2.5 with a residual/target)
PIXEL_BYTES = {"forward": 16, "vjp": 40, "objective": 40}
#: per pixel whose rays may meet a surface: its index and how far its rays go (sub-rays are traced
#: in chunks of constant size)
RAY_BYTES = 16
#: per surface crossing kept for the gradient: pixel, face, barycentrics, 1/cos (Embree backends). The
#: raster backend keeps 32 bytes a crossing for vjp/objective only, and at most BUBSUB_RASTER_STORE_MB;
#: the count of crossings assumed here is an upper one (tests/test_service_budget.py measures the peak)
CROSSING_BYTES = 28
#: per fine (subdivided) vertex of one surface: the vertices, faces, normals, Embree scene
FINE_VERTEX_BYTES = 1024
#: what a call may use beyond the estimate: ray chunk temporaries, interpreter, the request body itself
#: (bounded separately by BUBSUB_MAX_BODY_BYTES)
OVERHEAD_BYTES = 64 << 20


@dataclass(frozen=True)
class Estimate:
    """Estimated memory of one computation, by part (bytes)."""

    op: str
    pixels: int
    rays: int  # pixels whose rays may meet a surface
    crossings: int
    fine_vertices: int
    response: int

    @property
    def total(self):
        return (PIXEL_BYTES[self.op] * self.pixels + RAY_BYTES * self.rays + CROSSING_BYTES * self.crossings
                + FINE_VERTEX_BYTES * self.fine_vertices + self.response)

    def describe(self):
        """The parts in words, for error messages."""
        return (f"{self.pixels} output pixels, {self.rays} of them traced, {self.crossings} crossings assumed, "
                f"{self.fine_vertices} fine vertices, {self.response}-byte response")


def _fine_vertices(group):
    """Fine vertices of one surface of ``group`` (exact once built, else Loop's count)."""
    if group.template is not None:
        return int(group.template.S.shape[0])
    if group.faces is None:
        return group.n_control << group.levels
    return len(group.faces) * 4 ** group.levels // 2 + 2


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
        lo, hi = v.min(axis=1), v.max(axis=1)
        centres.append((lo + hi) / 2)
        radii.append(np.linalg.norm(hi - lo, axis=1) / 2 * 1.001 + 1e-9)
    c = np.concatenate(centres)
    if job.ndim == 2:
        c = np.concatenate([c, np.zeros((len(c), 1))], axis=1)
    return c, np.concatenate(radii)


def _footprints(job, x):
    """``(pixels that may see a surface, sum over surfaces of the pixels whose rays may cross it)``.

    The same bound as the core projector's ray culling (each surface's sphere
    enclosed in a detector-aligned cube, its projected corners bounding the
    pixels it can shadow), vectorised over surfaces and without the per-pixel
    arrays: the first count is at most the pixels, the second counts a pixel
    once per surface over it.
    """
    f = job.projector._frames  # noqa: SLF001 - the projector's own detector frames
    centre, radius = _bounding_spheres(job, x)
    signs = np.array([[(i >> j) & 1 for j in range(3)] for i in range(8)], float) * 2 - 1
    per_view = f.rows * f.cols
    union = total = 0
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
        a = (rel @ np.cross(v, nrm) / (u @ np.cross(v, nrm))).reshape(-1, 8) + f.cols / 2 - 0.5
        cols = np.clip(np.ceil(a.max(1)) + 2, 0, f.cols) - np.clip(np.floor(a.min(1)) - 1, 0, f.cols)
        if f.ndim == 3:
            b = (rel @ np.cross(nrm, u) / (v @ np.cross(nrm, u))).reshape(-1, 8) + f.rows / 2 - 0.5
            rows = np.clip(np.ceil(b.max(1)) + 2, 0, f.rows) - np.clip(np.floor(b.min(1)) - 1, 0, f.rows)
        else:
            rows = 1
        boxes = cols * rows
        union += min(per_view, int(np.sum(boxes)))
        # a ray that crosses a surface passes through its sphere's disc, pi/4 of the enclosing square
        total += int(np.sum(np.ceil(np.pi / 4 * boxes))) if f.ndim == 3 else int(np.sum(boxes))
    return union, total


def estimate(job, op, crossings_per_ray, vertices=None):
    """Upper estimate of the memory of ``op`` on ``job``.

    Parameters
    ----------
    job : Job
    op : {"forward", "vjp", "objective"}
    crossings_per_ray : int
        Crossings a sub-ray is assumed to have with one surface it meets
        (``BUBSUB_CROSSINGS_PER_RAY``; 2 for convex bubbles).
    vertices : (n_control_total, ndim) float, optional
        Checked control vertices of the request: the sub-rays are those of the
        pixels that may see a surface. Without them only the parts that do
        not depend on the vertices are counted (rays and crossings: 0), as
        when a job is created.

    Returns
    -------
    Estimate
    """
    pixels = 1
    for n in job.geometry.shape:
        pixels *= int(n)
    k2 = job.supersampling ** 2
    union, total = (0, 0) if vertices is None else _footprints(job, vertices)
    rays = union
    crossings = total * k2 * int(crossings_per_ray)
    fine = sum(g.count * _fine_vertices(g) for g in job.groups)
    n_control = job.n_control * job.ndim * 8
    response = 4 * pixels if op == "forward" else 2 * n_control
    return Estimate(op, pixels, rays, crossings, fine, response + 256)


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
