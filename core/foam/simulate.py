"""Simulated CT scans of foam phantoms, with Poisson noise.

2D (as in the paper): the phantom is rasterised on a fine grid (2000 x 2000
pixels over the 10 mm square by default) and projected with one of ASTRA's
CPU voxel projectors, so the data do not come from the mesh model that is
fitted to them. 3D: the meshes are projected exactly with
:class:`bubsub.core.MeshProjector`.

Noise: with ``photons = I0`` flat-field counts per detector pixel, counts
are drawn ``~ Poisson(I0 exp(-p))`` and the noisy line integral is
``-log(max(counts, 1) / I0)``. The noise-free projection of the liquid
container alone is returned as the scan's ``background``, so that the fit
uses ``data - background`` (the bubbles' projection, negative).

ASTRA and bubsub agree on conventions because the geometry is handed to
ASTRA as its own vector geometry (``geometry.to_astra()``) and the image is
laid out as ASTRA's 2D volume (row 0 at y max).
"""

from __future__ import annotations

import numbers

import numpy as np

from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.foam.phantoms import FoamPhantom
from bubsub.core.projection.masks import check_grid
from bubsub.core.io.scanfile import Scan
from bubsub.core.validate import check_int
from bubsub.core.projection.projector import MeshProjector
from bubsub.core.voxel.astra2d import AstraProjector2D, have_astra as _have_astra

__all__ = [
    "project_image",
    "add_poisson_noise",
    "simulate_2d",
    "simulate_3d",
    "default_geometry_2d",
    "default_geometry_3d",
    "simulated_scan",
    "ASTRA_PROJECTORS",
]

#: ASTRA CPU projector types usable per 2D geometry kind ("auto" picks the first).
ASTRA_PROJECTORS = {
    "parallel_vec": ("linear", "strip", "line"),
    "fanflat_vec": ("line_fanflat",),
}


# -- geometries ------------------------------------------------------------------------
def default_geometry_2d(n_angles=100, *, det_count=2400, pixel_size=0.006):
    """Parallel-beam 2D scan over [0, pi) as in the paper's 2D experiments.

    The default detector (2400 pixels of 0.006 mm = 14.4 mm) is wider than
    the diagonal of the 10 mm phantom square (14.14 mm), so no projection is
    truncated.

    Parameters
    ----------
    n_angles : int
        Equiangular projections in [0, pi).
    det_count : int
    pixel_size : float
        Detector pixel width, mm.

    Returns
    -------
    ScanGeometry
        Kind ``parallel_vec``, shape ``(n_angles, det_count)``.
    """
    n = check_int(n_angles, "n_angles", 1)
    angles = np.linspace(0.0, np.pi, n, endpoint=False)
    return ScanGeometry.parallel(angles, pixel_size=pixel_size, cols=det_count)


def default_geometry_3d(
    n_angles=25,
    *,
    rows=256,
    cols=512,
    source_origin=150.0,
    origin_detector=150.0,
    size=(20.0, 20.0, 10.0),
    pixel_size=None,
):
    """Circular cone-beam scan over [0, 2 pi) as in the paper's 3D experiments.

    Parameters
    ----------
    n_angles : int
        Equiangular projections in [0, 2 pi).
    rows, cols : int
        Detector size (256 x 512 in the paper).
    source_origin, origin_detector : float
        Source-axis and axis-detector distances, mm.
    size : (3,) float
        Object box (x, y, z), mm, centred at the origin; used to choose the
        pixel size.
    pixel_size : float, optional
        Detector pixel size, mm; by default the smallest square pixel whose
        detector sees the whole box from every angle (with 2 % slack).

    Returns
    -------
    ScanGeometry
        Kind ``cone_vec``, shape ``(n_angles, rows, cols)``.
    """
    n = check_int(n_angles, "n_angles", 1)
    rows, cols = check_int(rows, "rows", 1), check_int(cols, "cols", 1)
    so, od = float(source_origin), float(origin_detector)
    if pixel_size is None:
        sx, sy, sz = (float(v) for v in np.broadcast_to(np.asarray(size, dtype=float), (3,)))
        r = 0.5 * np.hypot(sx, sy)  # radius of the box's footprint around the axis
        if not so > r:
            raise ValueError(f"source_origin={so} must exceed the object's radius {r:.3g} mm")
        mag = (so + od) / (so - r)  # largest magnification, at the point nearest the source
        pixel_size = float(1.02 * max(2 * r * mag / cols, sz * mag / rows))
    angles = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return ScanGeometry.cone(
        angles, source_origin=so, origin_detector=od, pixel_size=pixel_size, cols=cols, rows=rows
    )


# -- building blocks ---------------------------------------------------------------------
def project_image(image, extent, geometry, projector="auto"):
    """Project a 2D attenuation image with an ASTRA CPU projector.

    Parameters
    ----------
    image : (rows, cols) float
        Attenuation, 1/mm, laid out as in ``docs/architecture.md`` (row 0 at y max).
    extent : (xmin, xmax, ymin, ymax)
        Image extent, mm; pixels must be square.
    geometry : ScanGeometry
        A 2D geometry (``parallel_vec`` or ``fanflat_vec``).
    projector : str
        ``"auto"`` or an ASTRA projector type allowed for the geometry kind
        (:data:`ASTRA_PROJECTORS`): ``linear`` (Joseph), ``strip`` or
        ``line`` for parallel beams, ``line_fanflat`` for fan beams.

    Returns
    -------
    (n_angles, det_count) float32
        Line integrals.
    """
    if not _have_astra():  # pragma: no cover - depends on the environment
        raise ImportError(
            "voxel projection needs the ASTRA toolbox (pip install astra-toolbox, or bubsub[astra]); "
            "simulate_2d(..., method='mesh') works without it"
        )
    if not isinstance(geometry, ScanGeometry) or geometry.ndim != 2:
        raise ValueError("project_image needs a 2D ScanGeometry (parallel_vec or fanflat_vec)")
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"image must be 2D (rows, cols), got shape {img.shape}")
    if not np.issubdtype(img.dtype, np.number):
        raise ValueError(f"image must be numeric, got dtype {img.dtype}")
    (rows, cols), ext = check_grid(img.shape, extent)
    px, py = (ext[1] - ext[0]) / cols, (ext[3] - ext[2]) / rows
    if not np.isclose(px, py, rtol=1e-9, atol=0):
        raise ValueError(f"image pixels must be square for ASTRA, got {px} x {py} mm")
    if not np.all(np.isfinite(img)):
        raise ValueError("image contains NaN or inf")
    allowed = ASTRA_PROJECTORS[geometry.kind]
    ptype = allowed[0] if projector == "auto" else projector
    if ptype not in allowed:
        raise ValueError(f"projector {projector!r} does not support {geometry.kind}; use one of {allowed}")
    with AstraProjector2D(geometry, (rows, cols), ext, projector=ptype) as op:
        return op.forward(img).reshape(geometry.shape)


def add_poisson_noise(projections, photons, seed=0):
    """Poisson noise for line integrals at a flat-field photon count.

    ``counts ~ Poisson(photons * exp(-p))``, returned as
    ``-log(max(counts, 1) / photons)``.

    Parameters
    ----------
    projections : ndarray
        Noise-free line integrals (any shape).
    photons : float
        Flat-field photon count per detector pixel (I0), > 0.
    seed : int
        Seed of the numpy Generator.

    Returns
    -------
    ndarray of float32, same shape
    """
    i0 = float(photons) if isinstance(photons, numbers.Real) and not isinstance(photons, bool) else None
    if i0 is None or not np.isfinite(i0) or i0 <= 0:
        raise ValueError(f"photons must be a positive number, got {photons!r}")
    rng = _rng(seed)
    p = np.asarray(projections, dtype=np.float64)
    if not np.all(np.isfinite(p)):
        raise ValueError("projections contain NaN or inf")
    counts = rng.poisson(i0 * np.exp(-p))
    return (-np.log(np.maximum(counts, 1) / i0)).astype(np.float32)


# -- scans ---------------------------------------------------------------------------------
def simulate_2d(
    phantom,
    geometry,
    *,
    photons=None,
    seed=0,
    image_size=2000,
    supersample=1,
    method="voxel",
    projector="auto",
):
    """Simulated 2D scan of a foam phantom.

    Parameters
    ----------
    phantom : FoamPhantom
        A 2D phantom (:func:`bubsub.core.foam.phantoms.foam2d`).
    geometry : ScanGeometry
        ``parallel_vec`` or ``fanflat_vec``, e.g. :func:`default_geometry_2d`.
    photons : float, optional
        Flat-field photon count per pixel; ``None`` gives noise-free data.
    seed : int
        Seed of the noise.
    image_size : int or (rows, cols)
        Rasterisation grid over the phantom's square (``method="voxel"``).
    supersample : int
        Sub-samples per pixel and axis in the rasterisation.
    method : {"voxel", "mesh"}
        ``"voxel"`` (paper): ASTRA projection of the rasterised image.
        ``"mesh"``: exact projection of the polygons with MeshProjector.
    projector : str
        ASTRA projector type (see :func:`project_image`).

    Returns
    -------
    Scan
        ``data`` (noisy if ``photons``), ``background`` (noise-free
        projection of the liquid square alone, made the same way),
        ``bubble_contrast = phantom.contrast``, ``attrs`` with the
        simulation settings.
    """
    _check_phantom(phantom, 2)
    if not isinstance(geometry, ScanGeometry) or geometry.ndim != 2:
        raise ValueError("simulate_2d needs a 2D ScanGeometry (parallel_vec or fanflat_vec)")
    if method == "voxel":
        shape, extent = phantom.grid(image_size)
        full = phantom.attenuation_image(shape, extent, supersample=supersample, dtype=np.float32)
        liquid = phantom.liquid_image(shape, extent, supersample=supersample, dtype=np.float32)
        clean = project_image(full, extent, geometry, projector)
        background = project_image(liquid, extent, geometry, projector)
        info = {"image_rows": shape[0], "image_cols": shape[1], "supersample": supersample,
                "projector": projector if projector != "auto" else ASTRA_PROJECTORS[geometry.kind][0]}
    elif method == "mesh":
        proj = MeshProjector(geometry)
        clean = proj.forward(phantom.items)
        background = proj.forward([phantom.liquid])
        info = {}
    else:
        raise ValueError(f"method must be 'voxel' or 'mesh', got {method!r}")
    return simulated_scan(phantom, geometry, clean, background, photons, seed, method, info)


def simulate_3d(phantom, geometry, *, photons=None, seed=0, supersampling=1, threads=None):
    """Simulated 3D scan of a foam phantom with the exact mesh projector.

    Parameters
    ----------
    phantom : FoamPhantom
        A 3D phantom (:func:`bubsub.core.foam.phantoms.foam3d`, :func:`foam3d_benchmark`).
    geometry : ScanGeometry
        ``cone_vec`` or ``parallel3d_vec``, e.g. :func:`default_geometry_3d`.
    photons : float, optional
        Flat-field photon count per pixel; ``None`` gives noise-free data.
    seed : int
        Seed of the noise.
    supersampling : int
        Rays per pixel and axis (``MeshProjector(supersampling=)``).
    threads : int, optional
        Projector threads.

    Returns
    -------
    Scan
        As :func:`simulate_2d`; shapes ``(n_angles, rows, cols)``.
    """
    _check_phantom(phantom, 3)
    if not isinstance(geometry, ScanGeometry) or geometry.ndim != 3:
        raise ValueError("simulate_3d needs a 3D ScanGeometry (cone_vec or parallel3d_vec)")
    proj = MeshProjector(geometry, supersampling=supersampling, threads=threads)
    clean = proj.forward(phantom.items)
    background = proj.forward([phantom.liquid])
    return simulated_scan(phantom, geometry, clean, background, photons, seed, "mesh", {"supersampling": supersampling})


def simulated_scan(phantom, geometry, clean, background, photons, seed, method, info):
    """The :class:`Scan` of a simulation: its noisy data (Poisson at ``photons``, or ``clean`` itself),
    the liquid alone as background, and the attributes that say how it was made.

    Parameters
    ----------
    phantom : FoamPhantom
        Its contrast, seed and bubble count go into the scan.
    geometry : ScanGeometry
    clean, background : (n_angles, [rows,] cols) float
        Noise-free projections of the foam and of the liquid alone.
    photons : float or None
        Incident photons per pixel; None for no noise.
    seed : int
        Of the noise.
    method : str
        ``attrs["method"]``.
    info : dict
        More attributes.
    """
    data = clean if photons is None else add_poisson_noise(clean, photons, seed)
    attrs = {"simulated": 1, "method": method, "photons": 0.0 if photons is None else float(photons)}
    if photons is not None:
        attrs["noise_seed"] = int(seed)
    if phantom.seed is not None:
        attrs["phantom_seed"] = int(phantom.seed)
    attrs["n_bubbles"] = len(phantom.bubbles)
    attrs.update(info)
    return Scan(
        data=np.asarray(data, dtype=np.float32),
        geometry=geometry,
        background=np.asarray(background, dtype=np.float32),
        bubble_contrast=phantom.contrast,
        attrs=attrs,
    )


def _check_phantom(phantom, ndim):
    if not isinstance(phantom, FoamPhantom):
        raise ValueError(f"phantom must be a FoamPhantom, got {type(phantom).__name__}")
    if phantom.ndim != ndim:
        raise ValueError(f"a {ndim}D simulation needs a {ndim}D phantom, got a {phantom.ndim}D one")




def _rng(seed):
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return np.random.default_rng(int(seed))
