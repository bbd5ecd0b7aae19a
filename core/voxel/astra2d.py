"""2D voxel (pixel) reconstruction with ASTRA's CPU projectors: FBP, SIRT, CGLS, LSQR, TV.

Images follow the convention of :mod:`bubsub.core.voxel.grid`: ``img[row, col]``,
row 0 at y max, ``extent = (xmin, xmax, ymin, ymax)`` (ASTRA's 2D volume
geometry). Sinograms are ``(angle, col)``.

ASTRA (``astra-toolbox``, an optional dependency) provides the projector
for ``backend='astra'``; ``backend='numpy'`` uses
:class:`bubsub.core.voxel.projector3d.VoxelProjector` instead and needs no ASTRA.
ASTRA's CPU ``FBP`` only handles plain ``parallel`` geometries, so FBP runs
through ASTRA only for a parallel-beam vector geometry that is one (rays
perpendicular to a centred detector); every other case (fan beams, shifted
or tilted detectors) uses the numpy FBP/FDK of
:func:`bubsub.core.voxel.projector3d.fdk`.
"""

from __future__ import annotations

import numpy as np

from bubsub.core.voxel import solvers
from bubsub.core.voxel.grid import resolve_grid
from bubsub.core.voxel.fdk import FILTERS, fdk
from bubsub.core.voxel.projector3d import VoxelProjector, as_scan_geometry
from bubsub.core.voxel.reconstruct3d import check_upper, iterate

__all__ = ["AstraProjector2D", "fbp_2d", "reconstruct_2d", "astra_vol_geom", "have_astra", "METHODS_2D"]

#: Methods of :func:`reconstruct_2d` and their default iteration counts.
METHODS_2D = {"fbp": None, "sirt": 200, "cgls": 30, "lsqr": 30, "tv": 300, "bb": 30}

_F32 = np.float32


def _astra():
    try:
        import astra
    except ImportError:  # pragma: no cover - depends on the environment
        raise ImportError(
            "backend='astra' needs the ASTRA toolbox (pip install astra-toolbox, or bubsub[astra]); "
            "use backend='numpy' instead"
        ) from None
    return astra


def have_astra():
    """Whether the ASTRA toolbox can be imported (the 2D voxel route falls back to numpy without it)."""
    try:
        import astra  # noqa: F401
    except ImportError:
        return False
    return True



def astra_vol_geom(shape, extent):
    """ASTRA 2D volume geometry of a grid.

    Parameters
    ----------
    shape : (rows, cols)
    extent : (xmin, xmax, ymin, ymax)

    Returns
    -------
    dict
        ``astra.create_vol_geom(rows, cols, xmin, xmax, ymin, ymax)``.
    """
    astra = _astra()
    (rows, cols), ext = resolve_grid(shape, extent)
    return astra.create_vol_geom(rows, cols, ext[0], ext[1], ext[2], ext[3])


def _check_2d(geom):
    if geom.ndim != 2:
        raise ValueError(f"2D reconstruction needs a 2D geometry (parallel_vec or fanflat_vec), got {geom.kind}")


def _default_projector(geom):
    return "line_fanflat" if geom.kind == "fanflat_vec" else "linear"


class AstraProjector2D:
    """ASTRA CPU projector for a 2D scan and pixel grid, with forward and adjoint.

    The backprojection is ASTRA's ``BP`` with the same projector, the exact
    transpose of its ``FP``.

    Parameters
    ----------
    geometry : ScanGeometry or ASTRA proj_geom dict
        ``parallel_vec`` or ``fanflat_vec`` (or a plain ``parallel``/``fanflat`` dict).
    shape : (rows, cols)
    extent : (xmin, xmax, ymin, ymax), optional
    pixel_size, centre : optional
        Instead of ``extent`` (see :func:`bubsub.core.voxel.grid.resolve_grid`).
    projector : str, optional
        ASTRA CPU projector type: ``linear`` (default), ``line``, ``strip`` or
        ``distance_driven`` for parallel beams; ``line_fanflat`` (default)
        for fan beams.

    Attributes
    ----------
    shape : (rows, cols)
    proj_shape : (n_angles, det_count)
    extent : tuple
    projector_id : int
        The ASTRA projector (freed by :meth:`close`).
    """

    def __init__(self, geometry, shape, extent=None, *, pixel_size=None, centre=None, projector=None):
        astra = _astra()
        self.geometry = as_scan_geometry(geometry)
        _check_2d(self.geometry)
        self.grid = resolve_grid(shape, extent, pixel_size, centre)
        self.shape, self.extent = self.grid
        if len(self.shape) != 2:
            raise ValueError(f"a 2D geometry needs a 2D grid (rows, cols), got {self.shape}")
        self.proj_shape = self.geometry.shape
        self.vol_geom = astra_vol_geom(self.shape, self.extent)
        self.proj_geom = self.geometry.to_astra()
        self.projector = projector or _default_projector(self.geometry)
        self._ids = []
        try:
            self.projector_id = astra.create_projector(self.projector, self.proj_geom, self.vol_geom)
        except Exception as exc:
            raise ValueError(
                f"ASTRA projector {self.projector!r} does not support {self.geometry.kind}: {exc}"
            ) from None
        self._vol_id = astra.data2d.create("-vol", self.vol_geom, 0.0)
        self._sino_id = astra.data2d.create("-sino", self.proj_geom, 0.0)
        self._ids = [self._vol_id, self._sino_id]
        cfg = astra.astra_dict("FP")
        cfg.update(ProjectorId=self.projector_id, ProjectionDataId=self._sino_id, VolumeDataId=self._vol_id)
        self._fp = astra.algorithm.create(cfg)
        cfg = astra.astra_dict("BP")
        cfg.update(ProjectorId=self.projector_id, ProjectionDataId=self._sino_id, ReconstructionDataId=self._vol_id)
        self._bp = astra.algorithm.create(cfg)

    def forward(self, image):
        """Project an image (rows, cols) -> sinogram (n_angles, det_count) float32."""
        astra = _astra()
        x = np.asarray(image)
        if x.shape != tuple(self.shape):
            raise ValueError(f"image must have shape {tuple(self.shape)}, got {x.shape}")
        astra.data2d.store(self._vol_id, np.ascontiguousarray(x, dtype=_F32))
        astra.algorithm.run(self._fp)
        return np.array(astra.data2d.get_shared(self._sino_id), dtype=_F32)

    def adjoint(self, sinogram):
        """Backproject a sinogram (n_angles, det_count) -> image (rows, cols) float32."""
        astra = _astra()
        y = np.asarray(sinogram)
        if y.shape != tuple(self.proj_shape):
            raise ValueError(f"sinogram must have shape {tuple(self.proj_shape)}, got {y.shape}")
        astra.data2d.store(self._sino_id, np.ascontiguousarray(y, dtype=_F32))
        astra.algorithm.run(self._bp)
        return np.array(astra.data2d.get_shared(self._vol_id), dtype=_F32)

    def run_algorithm(self, name, sinogram, iterations, x0=None, options=None):
        """Run an ASTRA CPU algorithm (``SIRT``, ``CGLS``, ``SART``, ...) with this projector.

        Returns the reconstruction (rows, cols) float32.
        """
        astra = _astra()
        y = np.asarray(sinogram)
        if y.shape != tuple(self.proj_shape):
            raise ValueError(f"sinogram must have shape {tuple(self.proj_shape)}, got {y.shape}")
        astra.data2d.store(self._sino_id, np.ascontiguousarray(y, dtype=_F32))
        if x0 is None:
            astra.data2d.store(self._vol_id, 0.0)
        else:
            x0 = np.asarray(x0)
            if x0.shape != tuple(self.shape):
                raise ValueError(f"x0 must have shape {tuple(self.shape)}, got {x0.shape}")
            astra.data2d.store(self._vol_id, np.ascontiguousarray(x0, dtype=_F32))
        cfg = astra.astra_dict(name)
        cfg.update(ProjectorId=self.projector_id, ProjectionDataId=self._sino_id, ReconstructionDataId=self._vol_id)
        if options:
            cfg["option"] = dict(options)
        alg = astra.algorithm.create(cfg)
        try:
            astra.algorithm.run(alg, int(iterations))
        finally:
            astra.algorithm.delete(alg)
        return np.array(astra.data2d.get_shared(self._vol_id), dtype=_F32)

    def close(self):
        """Free the ASTRA objects (idempotent)."""
        try:
            import astra
        except ImportError:  # pragma: no cover
            return
        for name in ("_fp", "_bp"):
            alg = self.__dict__.pop(name, None)
            if alg is not None:
                astra.algorithm.delete(alg)
        if self._ids:
            astra.data2d.delete(self._ids)
            self._ids = []
        pid = self.__dict__.pop("projector_id", None)
        if pid is not None:
            astra.projector.delete(pid)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass


def _as_plain_parallel(geom, tol=1e-9):
    """ASTRA ``parallel`` proj_geom equal to a ``parallel_vec`` geometry, or None."""
    if geom.kind != "parallel_vec":
        return None
    v = geom.vectors
    ray, d, u = v[:, 0:2], v[:, 2:4], v[:, 4:6]
    width = np.linalg.norm(u, axis=1)
    if not np.allclose(width, width[0], rtol=tol, atol=0):
        return None
    uhat = u / width[:, None]
    rhat = ray / np.linalg.norm(ray, axis=1, keepdims=True)
    # ASTRA parallel: ray = (sin t, -cos t), u = w (cos t, sin t), d = 0
    if not np.allclose(rhat, np.stack([uhat[:, 1], -uhat[:, 0]], axis=1), atol=tol):
        return None
    if not np.allclose(np.sum(d * uhat, axis=1), 0, atol=tol * max(1.0, width[0])):
        return None
    angles = np.arctan2(uhat[:, 1], uhat[:, 0])
    astra = _astra()
    return astra.create_proj_geom("parallel", float(width[0]), geom.det_cols, angles)


def fbp_2d(sinogram, geometry, shape, extent=None, *, pixel_size=None, centre=None, filter="ram-lak", backend="auto"):
    """Filtered backprojection of a 2D parallel- or fan-beam sinogram.

    Parameters
    ----------
    sinogram : (n_angles, det_count) float
    geometry : ScanGeometry or ASTRA proj_geom dict (2D)
    shape : (rows, cols)
    extent, pixel_size, centre
        The grid.
    filter : str
        One of :data:`bubsub.core.voxel.projector3d.FILTERS`.
    backend : {'auto', 'astra', 'numpy'}
        ``astra``: ASTRA's CPU ``FBP`` (plain parallel geometries only, else
        ValueError); ``numpy``: :func:`bubsub.core.voxel.projector3d.fdk` (any 2D
        geometry; full 360 degree orbit for fan beams); ``auto``: ASTRA where
        it applies and is installed, else numpy.

    Returns
    -------
    (rows, cols) float32
        Attenuation, 1/mm.
    """
    geom = as_scan_geometry(geometry)
    _check_2d(geom)
    if filter not in FILTERS:
        raise ValueError(f"unknown filter {filter!r}; expected one of {FILTERS}")
    if backend not in ("auto", "astra", "numpy"):
        raise ValueError(f"backend must be 'auto', 'astra' or 'numpy', got {backend!r}")
    shp, ext = resolve_grid(shape, extent, pixel_size, centre)
    if len(shp) != 2:
        raise ValueError(f"a 2D geometry needs a 2D grid (rows, cols), got {shp}")
    sino = np.asarray(sinogram)
    if sino.shape != geom.shape:
        raise ValueError(f"sinogram must have shape {geom.shape}, got {sino.shape}")
    if not np.all(np.isfinite(sino)):
        raise ValueError("sinogram contains NaN or inf")
    use_astra = backend == "astra"
    plain = None
    if backend in ("auto", "astra"):
        try:
            plain = _as_plain_parallel(geom)
        except ImportError:
            if backend == "astra":
                raise
            plain = None
        if backend == "astra" and plain is None:
            raise ValueError(
                "ASTRA's CPU FBP only supports plain parallel-beam geometries (rays perpendicular to a "
                f"centred detector); this {geom.kind} geometry is not one: use backend='numpy'"
            )
        use_astra = plain is not None
    if not use_astra:
        return fdk(sino, geom, shp, ext, filter=filter)
    astra = _astra()
    vol_geom = astra_vol_geom(shp, ext)
    pid = astra.create_projector("linear", plain, vol_geom)
    sid = astra.data2d.create("-sino", plain, np.ascontiguousarray(sino, dtype=_F32))
    rid = astra.data2d.create("-vol", vol_geom, 0.0)
    try:
        cfg = astra.astra_dict("FBP")
        cfg.update(ProjectorId=pid, ProjectionDataId=sid, ReconstructionDataId=rid, FilterType=filter)
        alg = astra.algorithm.create(cfg)
        try:
            astra.algorithm.run(alg)
        finally:
            astra.algorithm.delete(alg)
        return np.array(astra.data2d.get(rid), dtype=_F32)
    finally:
        astra.data2d.delete([sid, rid])
        astra.projector.delete(pid)


def reconstruct_2d(
    method,
    sinogram,
    geometry,
    shape,
    extent=None,
    *,
    pixel_size=None,
    centre=None,
    iterations=None,
    tv_weight=None,
    nonneg=False,
    filter="ram-lak",
    isotropic=True,
    projector=None,
    backend="auto",
    x0=None,
    upper=None,
    callback=None,
):
    """Voxel reconstruction of a 2D sinogram.

    Parameters
    ----------
    method : {'fbp', 'sirt', 'cgls', 'lsqr', 'tv', 'bb'}
        ``fbp``: :func:`fbp_2d`; ``sirt`` / ``cgls``: ASTRA's CPU algorithms
        (``backend='astra'``; CGLS with ``x0`` or a callback, and SIRT with a
        callback, use :mod:`bubsub.core.voxel.solvers` on the ASTRA projector) or
        :mod:`bubsub.core.voxel.solvers` (``backend='numpy'``); ``lsqr``: scipy
        LSQR; ``tv``: :func:`bubsub.core.voxel.solvers.tv_pdhg` (total variation
        by preconditioned Chambolle-Pock).
    sinogram : (n_angles, det_count) float
        Line integrals (dimensionless), ``geometry.shape``.
    geometry : ScanGeometry or ASTRA proj_geom dict
        ``parallel_vec`` or ``fanflat_vec``.
    shape : (rows, cols)
    extent : (xmin, xmax, ymin, ymax), optional
    pixel_size, centre : optional
        Instead of ``extent``: square pixel size (mm) and grid centre [x, y].
    iterations : int, optional
        Defaults from :data:`METHODS_2D`.
    tv_weight : float
        Required for ``tv``: weight of ``int |grad f|`` (see :func:`bubsub.core.voxel.solvers.tv_pdhg`).
    nonneg : bool
        Non-negativity for ``sirt`` (ASTRA ``MinConstraint``) and ``tv``.
    filter : str
        FBP filter (:data:`bubsub.core.voxel.projector3d.FILTERS`).
    isotropic : bool
        Isotropic (True) or anisotropic (l1) TV.
    projector : str, optional
        ASTRA projector type (see :class:`AstraProjector2D`).
    backend : {'auto', 'astra', 'numpy'}
        Projector for the iterative methods: ASTRA's CPU projector or
        :class:`bubsub.core.voxel.projector3d.VoxelProjector`; ``auto`` is ASTRA when
        it is installed. FBP uses ASTRA when it can (see :func:`fbp_2d`)
        unless ``backend='numpy'``.
    x0 : (rows, cols), optional
        Initial image for ``sirt``, ``cgls`` and ``tv``.
    upper : float, optional
        Upper bound on every pixel (``bb`` only: projected onto before each gradient).
    callback : callable(k, x), optional
        Per-iteration callback (numpy solvers only: not with ASTRA's SIRT/CGLS).

    Returns
    -------
    (rows, cols) float32
        Attenuation, 1/mm, row 0 at y max.
    """
    if method not in METHODS_2D:
        raise ValueError(f"unknown method {method!r}; expected one of {sorted(METHODS_2D)}")
    check_upper(method, upper)
    if backend not in ("auto", "astra", "numpy"):
        raise ValueError(f"backend must be 'auto', 'astra' or 'numpy', got {backend!r}")
    if backend == "auto":
        backend = "astra" if have_astra() else "numpy"
    geom = as_scan_geometry(geometry)
    _check_2d(geom)
    if method == "fbp":
        return fbp_2d(sinogram, geom, shape, extent, pixel_size=pixel_size, centre=centre, filter=filter,
                      backend="auto" if backend == "astra" else "numpy")
    sino = np.asarray(sinogram, dtype=_F32)
    if sino.shape != geom.shape:
        raise ValueError(f"sinogram must have shape {geom.shape}, got {sino.shape}")
    if not np.all(np.isfinite(sino)):
        raise ValueError("sinogram contains NaN or inf")
    it = METHODS_2D[method] if iterations is None else solvers.check_iterations(iterations)
    if backend == "numpy":
        op = VoxelProjector(geom, shape, extent, pixel_size=pixel_size, centre=centre)
        return iterate(method, op, sino, it, tv_weight, nonneg, isotropic, x0, callback, METHODS_2D, upper=upper)
    with AstraProjector2D(geom, shape, extent, pixel_size=pixel_size, centre=centre, projector=projector) as op:
        if method == "sirt" and callback is None:
            return op.run_algorithm("SIRT", sino, it, x0=x0, options={"MinConstraint": 0.0} if nonneg else None)
        if method == "cgls" and callback is None and x0 is None:
            # ASTRA 2.5's CPU CGLS mishandles a non-zero initial image (its error grows), so
            # a warm start goes through bubsub.core.voxel.solvers.cgls on the same projector.
            return op.run_algorithm("CGLS", sino, it)
        return iterate(method, op, sino, it, tv_weight, nonneg, isotropic, x0, callback, METHODS_2D, upper=upper)
