"""Shared fixtures and independent reference computations for the tests."""

import zlib

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from bubsub.core import Mesh


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
