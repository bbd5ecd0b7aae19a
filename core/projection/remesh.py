"""Warm starts for dynamic scans: a bubble's control mesh shrunk and remeshed.

Going backwards in time, each subscan starts from its successor's result:
every bubble's control mesh is shrunk toward its centroid (the paper's public
scripts use 0.8: bubbles grow, so earlier they are smaller) and made regular
again, because a fit stretches some control edges and squeezes others.

* 3D: isotropic remeshing (Botsch and Kobbelt: split long edges, collapse
  short ones, flip, smooth, project back) with gpytoolbox's
  ``remesh_botsch``, target edge length proportional to the bubble's size,
  so that a sphere gets about as many control points as the initial
  icosphere.
* 2D: the control polygon is resampled at evenly spaced arc lengths.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from bubsub.core.projection.mesh import Mesh, Polygon
from bubsub.core.projection.subdivision import SubdivisionSurface, sphere_surface

__all__ = ["shrink_toward_centroid", "resample_polygon", "remesh_isotropic", "warm_start"]

#: The paper's shrink factor for warm starts.
SHRINK = 0.8


def shrink_toward_centroid(vertices, centroid, factor):
    """``centroid + factor * (vertices - centroid)``; ``vertices (n, d)``, ``centroid (d,)``."""
    v = np.asarray(vertices, dtype=float)
    c = np.asarray(centroid, dtype=float).reshape(1, -1)
    if not 0 < factor <= 1.5:
        raise ValueError(f"shrink factor must be in (0, 1.5], got {factor!r}")
    return c + factor * (v - c)


def resample_polygon(vertices, n):
    """``n`` points evenly spaced by arc length along a closed polygon.

    Parameters
    ----------
    vertices : (m, 2) float
        Closed polygon (the last vertex connects to the first), mm.
    n : int
        Points wanted (>= 3).

    Returns
    -------
    (n, 2) float
        Starting at ``vertices[0]``, same orientation.
    """
    v = np.asarray(vertices, dtype=float)
    if v.ndim != 2 or v.shape[1] != 2 or len(v) < 3:
        raise ValueError(f"vertices must have shape (m >= 3, 2), got {v.shape}")
    if int(n) < 3:
        raise ValueError(f"a polygon needs at least 3 points, got {n}")
    closed = np.vstack([v, v[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if not s[-1] > 0:
        raise ValueError("polygon has zero length")
    t = np.arange(int(n)) * s[-1] / int(n)
    return np.stack([np.interp(t, s, closed[:, 0]), np.interp(t, s, closed[:, 1])], axis=1)


@lru_cache(maxsize=8)
def _edge_per_radius(control, levels):
    """Mean control edge length of the initial icosphere divided by its equivalent radius."""
    control = sphere_surface(np.zeros(3), 1.0, 1.0, control=control, levels=levels).control
    return control.mean_edge / control.equivalent_radius


def remesh_isotropic(mesh, edge_length, iterations=10):
    """Isotropic remesh of a closed triangle mesh (gpytoolbox ``remesh_botsch``).

    Parameters
    ----------
    mesh : Mesh
    edge_length : float
        Target edge length, mm.
    iterations : int

    Returns
    -------
    Mesh
        Closed and consistently oriented (checked by :class:`Mesh`), same attenuation.
    """
    try:
        import warnings

        with warnings.catch_warnings():  # gpytoolbox imports deprecated numpy/scipy names
            warnings.simplefilter("ignore", DeprecationWarning)
            import gpytoolbox
    except ImportError:  # pragma: no cover - depends on the environment
        raise ImportError("remeshing 3D warm starts needs gpytoolbox (pip install 'bubsub[dynamic]')") from None
    if not edge_length > 0:
        raise ValueError(f"edge_length must be positive, got {edge_length!r}")
    # the C++ binding needs writeable arrays; Mesh arrays are read-only
    v = np.array(mesh.vertices, dtype=np.float64, order="C")
    f = np.array(mesh.faces, dtype=np.int32, order="C")
    u, g = gpytoolbox.remesh_botsch(v, f, i=int(iterations), h=float(edge_length), project=True)
    return Mesh(np.asarray(u, dtype=float), np.asarray(g, dtype=np.int64), mesh.attenuation)


def warm_start(surface, *, shrink=SHRINK, control_points=None):
    """A regular control mesh for the previous subscan, from a fitted bubble.

    Parameters
    ----------
    surface : SubdivisionSurface
        A fitted bubble (control mesh plus subdivision levels).
    shrink : float
        Factor toward the control mesh's centroid (0.8 in the paper's scripts).
    control_points : int, optional
        2D: points of the resampled control polygon (default: as many as
        now). 3D: the initial icosphere's control points (12, 42 or 162;
        default 42) that set the target edge length relative to the
        bubble's equivalent radius.

    Returns
    -------
    SubdivisionSurface
        Same levels and attenuation.

    Raises
    ------
    ValueError
        If the bubble has no positive area (volume) to remesh.
    """
    control = surface.control
    if isinstance(control, Polygon):
        if not control.area > 0:
            raise ValueError("bubble has no positive area")
        small = shrink_toward_centroid(control.vertices, control.centroid, shrink)
        n = int(control_points or len(small))
        return SubdivisionSurface(Polygon(resample_polygon(small, n), control.attenuation), surface.levels)
    volume = control.volume
    if not volume > 0:
        raise ValueError("bubble has no positive volume")
    small = control.with_vertices(shrink_toward_centroid(control.vertices, control.centroid, shrink))
    r_eq = shrink * control.equivalent_radius
    h = _edge_per_radius(int(control_points or 42), surface.levels) * r_eq
    return SubdivisionSurface(remesh_isotropic(small, h), surface.levels)
