"""A projection job: geometry, topology of the fitted surfaces, data, and the projector.

The job applies the subdivision itself: a request carries only the stacked
control vertices of all surfaces, which :meth:`Job.items` splits and turns
into :class:`~bubsub.core.SubdivisionSurface` objects sharing one subdivision
matrix per group (``with_vertices`` does no validation beyond shape and
finiteness, so an iteration costs a sparse product per surface).

Everything here is synchronous and runs in the compute pool's threads.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np

from bubsub.core import Mesh, MeshProjector, Polygon, ScanGeometry, SubdivisionSurface, loop_subdivision
from bubsub.core.projection.backends.base import check_deadline
from bubsub.service.errors import APIError

__all__ = ["Group", "Job", "regular_polygon", "topology_bytes", "build_job", "check_compute_timeout"]

_F32_MAX = float(np.finfo(np.float32).max)
#: values per block of :meth:`Job.check_projection` (16 MB of float32)
_CHECK_BLOCK = 1 << 22


def regular_polygon(n):
    """``n`` counter-clockwise points on the unit circle (a valid placeholder control polygon)."""
    a = 2.0 * np.pi * np.arange(n) / n
    return np.stack([np.cos(a), np.sin(a)], axis=1)


def topology_bytes(n_control, n_faces, levels):
    """Upper estimate of the bytes of S and the fine faces of one surface group.

    Parameters
    ----------
    n_control : int
    n_faces : int or None
        Control triangles (None for a 2D polygon).
    levels : int
    """
    if n_faces is None:
        n_fine = n_control * 2 ** levels
        return n_fine * 3 * 12 + (n_fine + 1) * 4
    m = n_faces * 4 ** levels
    n_fine = m // 2 + 2
    return n_fine * 16 * 12 + m * 24


def _sparse_nbytes(S):
    return int(S.data.nbytes + S.indices.nbytes + S.indptr.nbytes)


@dataclass
class Group:
    """``count`` surfaces sharing control topology, subdivision levels and attenuation.

    Attributes
    ----------
    n_control : int
        Control vertices per surface.
    faces : (m, 3) int64 or None
        Control triangles (3D); ``None`` for 2D control polygons.
    levels : int
    attenuation : float
    count : int
    template : SubdivisionSurface or None
        Built from the first valid control vertices seen; every iterate is
        ``template.with_vertices(x)``.
    """

    n_control: int
    faces: np.ndarray | None
    levels: int
    attenuation: float
    count: int = 1
    template: SubdivisionSurface | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def ndim(self):
        return 2 if self.faces is None else 3

    def build(self, vertices=None):
        """Make the template from control vertices (2D: a placeholder when none are given).

        Raises
        ------
        ValueError
            If the control mesh is invalid (open, inward, degenerate ...).
        """
        with self._lock:
            if self.template is not None:
                return self.template
            if self.faces is None:
                v = regular_polygon(self.n_control) if vertices is None else vertices
                control = Polygon(v, self.attenuation)
            else:
                if vertices is None:
                    return None
                control = Mesh(vertices, self.faces, self.attenuation)
            self.template = SubdivisionSurface(control, self.levels)
            return self.template

    def nbytes(self):
        """Bytes held: control faces and, once built, S and the fine faces."""
        n = 0 if self.faces is None else int(self.faces.nbytes)
        if self.template is not None:
            n += _sparse_nbytes(self.template.S)
            if self.template._topo.fine_faces is not None:  # noqa: SLF001 - size accounting only
                n += int(np.asarray(self.template._topo.fine_faces).nbytes)  # noqa: SLF001
        else:
            n += self.estimated_topology_bytes()
        return n

    def estimated_topology_bytes(self):
        """Upper estimate of S and fine faces before the template exists."""
        return topology_bytes(self.n_control, None if self.faces is None else len(self.faces), self.levels)


@dataclass
class Job:
    """One client's projection job (see module docstring).

    Attributes
    ----------
    id : str
        Unguessable id (``secrets.token_urlsafe``).
    owner : str
        Owner id from :class:`~bubsub.service.auth.TokenAuth`.
    geometry : ScanGeometry
    supersampling : int
    groups : list of Group
    projector : MeshProjector
    data, background : float32 arrays of ``geometry.shape`` or None
    target : float32 array or None
        ``data - background`` (or ``data``), the objective's default target.
    compute_timeout : float
        Seconds one computation may take (``BUBSUB_COMPUTE_TIMEOUT_SECONDS`` or less).
    """

    id: str
    owner: str
    geometry: ScanGeometry
    supersampling: int
    groups: list
    projector: MeshProjector
    data: np.ndarray | None = None
    background: np.ndarray | None = None
    target: np.ndarray | None = None
    compute_timeout: float = 120.0
    created: float = field(default_factory=time.time)
    last_used: float = field(default_factory=time.monotonic)
    active: int = 0
    compute_seconds: float = 0.0
    calls: int = 0

    # -- topology ----------------------------------------------------------------
    @property
    def ndim(self):
        return self.geometry.ndim

    @property
    def n_surfaces(self):
        return sum(g.count for g in self.groups)

    @property
    def n_control(self):
        """Total control vertices, the rows of a vertices body."""
        return sum(g.count * g.n_control for g in self.groups)

    @property
    def vertices_shape(self):
        return (self.n_control, self.ndim)

    def nbytes(self, data=..., background=...):
        """Bytes held by the job, optionally as if ``data``/``background`` were replaced."""
        data = self.data if data is ... else data
        background = self.background if background is ... else background
        n = int(self.geometry.vectors.nbytes) + sum(g.nbytes() for g in self.groups)
        for a in (data, background):
            if a is not None:
                n += int(a.nbytes)
        if data is not None and background is not None:
            n += int(data.nbytes)  # the cached target
        return n

    def touch(self):
        self.last_used = time.monotonic()

    # -- data --------------------------------------------------------------------
    def set_arrays(self, data=..., background=...):
        """Replace data and/or background (``None`` removes) and refresh the target.

        Raises
        ------
        APIError
            422 (and nothing changes) when ``data - background`` overflows float32.
        """
        self.data, self.background, self.target = self.arrays_with(data, background)

    def arrays_with(self, data=..., background=...):
        """``(data, background, target)`` as they would be after :meth:`set_arrays` (changes nothing).

        Raises
        ------
        APIError
            422 when ``data - background`` overflows float32.
        """
        data = self.data if data is ... else data
        background = self.background if background is ... else background
        if data is None:
            target = None
        elif background is None:
            target = data
        else:
            with np.errstate(over="ignore"):
                target = np.subtract(data, background, dtype=np.float32)
            if not np.all(np.isfinite(target)):
                raise APIError(422, "data minus background overflows float32; check the arrays' scale",
                               "out_of_range")
        return data, background, target

    # -- compute -----------------------------------------------------------------
    def check_vertices(self, x, name="vertices"):
        """Validate a stacked control-vertex array; returns it as float64."""
        if x.dtype.kind != "f":
            raise APIError(422, f"{name} must be float32 or float64, got dtype {x.dtype.str!r}", "bad_dtype")
        if x.shape != self.vertices_shape:
            raise APIError(422, f"{name} must have shape {self.vertices_shape} (all control vertices of the "
                                f"job's {self.n_surfaces} surfaces stacked), got {x.shape}", "bad_shape")
        x = np.asarray(x, dtype=np.float64)
        if not np.all(np.isfinite(x)):
            bad = int(np.count_nonzero(~np.isfinite(x).all(axis=1)))
            raise APIError(422, f"{name} contain NaN or inf ({bad} of {len(x)} vertices)", "not_finite")
        return x

    def check_projection(self, a, name, deadline=None):
        """Validate an array of the projection shape; returns a float32 copy.

        Block by block (:data:`_CHECK_BLOCK` values), ``deadline`` (a
        :func:`time.monotonic` value, for a computation's arrays) checked before
        each: checking and copying a scan's 31 million pixels into fresh pages
        takes a fair share of a second.
        """
        if a.dtype.kind not in "fiu":
            raise APIError(422, f"{name} must be a real float array, got dtype {a.dtype.str!r}", "bad_dtype")
        if a.shape != tuple(self.geometry.shape):
            raise APIError(422, f"{name} must have the projection shape {tuple(self.geometry.shape)} "
                                f"(angle, row, col / angle, col), got {a.shape}", "bad_shape")
        # float64 (or int64) beyond float32's range would be stored as inf and poison every objective
        wide = a.dtype.itemsize > 4 or a.dtype.kind != "f"
        src = a.reshape(-1)
        out = np.empty(a.shape, np.float32)
        dst = out.reshape(-1)
        big = 0.0
        for i in range(0, src.size, _CHECK_BLOCK):
            check_deadline(deadline)
            part = src[i:i + _CHECK_BLOCK]
            if not np.all(np.isfinite(part)):
                raise APIError(422, f"{name} contains NaN or inf", "not_finite")
            if wide:
                big = max(big, float(np.max(np.abs(part), initial=0.0)))
            if big <= _F32_MAX:  # past it the copy is refused below (after every block's NaN check)
                dst[i:i + _CHECK_BLOCK] = part
        if big > _F32_MAX:
            raise APIError(422, f"{name} has values up to {big:.4g}, outside float32's range "
                                f"(+-{_F32_MAX:.4g}); the server stores projections as float32", "out_of_range")
        return out

    def items(self, x):
        """The surfaces for stacked control vertices ``x`` (already checked)."""
        out = []
        pos = 0
        for g in self.groups:
            for _ in range(g.count):
                v = x[pos:pos + g.n_control]
                pos += g.n_control
                try:
                    template = g.template or g.build(v)
                    out.append(template.with_vertices(v))
                except ValueError as exc:
                    raise APIError(422, f"surface {len(out)}: {exc}", "invalid_surface") from None
        return out

    def deadline(self, spent=0.0):
        """The :func:`time.monotonic` value by which a computation starting now must end, ``spent``
        seconds of its request's work (decoding its body) already done."""
        return time.monotonic() + self.compute_timeout - spent

    def forward(self, x, deadline=None):
        """Projection of the surfaces, float32 of ``geometry.shape``.

        ``deadline`` (all three): past it the projector stops (within milliseconds)
        and raises :class:`~bubsub.core.projection.projector.DeadlineExceeded`.
        """
        return self.projector.forward(self.items(x), deadline)

    def vjp(self, x, residual, deadline=None):
        """Gradient w.r.t. the stacked control vertices of ``<forward, residual>``."""
        return np.concatenate(self.projector.vjp(self.items(x), residual, deadline), axis=0)

    def objective(self, x, data=None, deadline=None):
        """``(f, gradient)`` against ``data`` or, by default, the job's target."""
        target = self.target if data is None else data
        if target is None:
            raise APIError(409, "the job has no data: upload it (PUT /v1/jobs/{id}/data) or send "
                                "'data' with the request", "no_data")
        f, grads = self.projector.objective(self.items(x), target, deadline)
        return f, np.concatenate(grads, axis=0)


def build_geometry(spec):
    """:class:`ScanGeometry` from a :class:`~bubsub.service.schemas.GeometrySpec` (422 if invalid)."""
    try:
        if spec.kind in ("parallel_vec", "fanflat_vec"):
            if spec.det_rows is not None:
                raise ValueError(f"2D kind {spec.kind} takes det_cols only (det_rows must be null)")
            return ScanGeometry.from_astra(spec.kind, spec.vectors, det_count=spec.det_cols)
        if spec.det_rows is None:
            raise ValueError(f"3D kind {spec.kind} needs det_rows")
        return ScanGeometry.from_astra(spec.kind, spec.vectors, det_rows=spec.det_rows, det_cols=spec.det_cols)
    except (ValueError, TypeError) as exc:
        raise APIError(422, f"geometry: {exc}", "invalid_geometry") from None


def build_groups(specs, ndim):
    """Surface groups from their specs, with the control faces checked (422 if invalid)."""
    groups = []
    for k, s in enumerate(specs):
        if ndim == 2:
            if s.faces is not None:
                raise APIError(422, f"surfaces[{k}]: a 2D job's surfaces are control polygons; omit 'faces'",
                               "invalid_surface")
            faces = None
        else:
            if s.faces is None:
                raise APIError(422, f"surfaces[{k}]: a 3D job needs the control 'faces' (m, 3)", "invalid_surface")
            faces = np.asarray(s.faces, dtype=np.int64) if s.faces else np.empty((0, 3), np.int64)
            if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
                raise APIError(422, f"surfaces[{k}]: faces must have shape (m, 3) with m >= 1, got "
                                    f"{faces.shape}", "invalid_surface")
            lo, hi = int(faces.min()), int(faces.max())
            if lo < 0 or hi >= s.n_control:
                raise APIError(422, f"surfaces[{k}]: faces index vertices out of range [0, {s.n_control}): "
                                    f"min {lo}, max {hi}", "invalid_surface")
            faces.setflags(write=False)
        groups.append(Group(s.n_control, faces, s.levels, s.attenuation, s.count))
    return groups


def check_compute_timeout(spec, settings):
    """The job's compute timeout: what it asks for, at most the server's (422 beyond)."""
    limit = settings.compute_timeout_seconds
    asked = spec.compute_timeout_seconds
    if asked is None:
        return limit
    if asked > limit:
        raise APIError(422, f"compute_timeout_seconds {asked:g} is over the server's limit of {limit:g} s "
                            "(BUBSUB_COMPUTE_TIMEOUT_SECONDS); a job may ask for less, never more", "invalid")
    return float(asked)


def build_job(job_id, owner, spec, settings, vertices=None, data=None, background=None):
    """A validated :class:`Job` (runs in a worker thread: builds S and the projector).

    Parameters
    ----------
    job_id, owner : str
    spec : JobCreate
    settings : Settings
    vertices, data, background : numpy.ndarray, optional
        Initial control vertices (validates the control meshes now), data
        and background of the projection shape.

    Raises
    ------
    APIError
        422 for an invalid geometry, topology, vertices or array.
    """
    if spec.supersampling > settings.max_supersampling:
        raise APIError(422, f"supersampling {spec.supersampling} is over the server's limit of "
                            f"{settings.max_supersampling} (BUBSUB_MAX_SUPERSAMPLING)", "invalid")
    timeout = check_compute_timeout(spec, settings)
    geometry = build_geometry(spec.geometry)
    groups = build_groups(spec.surfaces, geometry.ndim)
    projector = MeshProjector(geometry, spec.supersampling, threads=settings.projector_threads)
    job = Job(job_id, owner, geometry, spec.supersampling, groups, projector, compute_timeout=timeout)
    arrays = {}
    if data is not None:
        arrays["data"] = job.check_projection(data, "data")
    if background is not None:
        arrays["background"] = job.check_projection(background, "background")
    if vertices is not None:
        x = job.check_vertices(vertices)
        pos = 0
        for k, g in enumerate(groups):
            try:
                template = g.build(x[pos:pos + g.n_control])
            except ValueError as exc:
                raise APIError(422, f"surfaces[{k}]: invalid control mesh: {exc}", "invalid_surface") from None
            for i in range(g.count):
                control = template.with_vertices(x[pos:pos + g.n_control]).control
                size = control.volume if g.ndim == 3 else control.area
                if not size > 0:
                    raise APIError(422, f"surfaces[{k}] #{i}: control {'mesh' if g.ndim == 3 else 'polygon'} "
                                        f"is inward/clockwise or degenerate (signed size {size:.3g})",
                                   "invalid_surface")
                pos += g.n_control
    else:
        for k, g in enumerate(groups):
            if g.ndim == 2:
                g.build()
            elif g.levels > 0:
                # Check the combinatorics (closed, manifold) now; orientation waits for vertices.
                try:
                    loop_subdivision(g.faces, g.n_control, 1)
                except ValueError as exc:
                    raise APIError(422, f"surfaces[{k}]: invalid control faces: {exc}", "invalid_surface") from None
    if "data" in arrays or "background" in arrays:
        job.set_arrays(**arrays)
    return job
