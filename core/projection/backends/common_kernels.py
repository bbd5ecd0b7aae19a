"""Compiled (numba) steps that every backend shares: the scene's face planes, the
gradient's scatter onto the vertices, and the objective's residual.

At fine subdivision a scene has hundreds of thousands of faces and a scan
millions of pixels; the numpy versions of these steps (gathers into
temporaries, three ``bincount`` passes, a float32 projection and a float64
residual written in two passes) cost as much as a quarter of an objective
evaluation, outside the backends' threads. Imported only when first used,
so that ``import bubsub`` does not import numba.
"""

from __future__ import annotations

import numba
import numpy as np

from bubsub.core.projection.backends.jit import cached

__all__ = ["triangle_planes", "scatter_face_sums", "residual"]

jit = cached(numba.njit, nogil=True, error_model="numpy")


@jit
def triangle_planes(vertices, faces, normals, offsets):
    """Unit normal ``(b - a) x (c - a) / |.|`` and plane offset ``n.a`` of every triangle (a, b, c).

    Parameters
    ----------
    vertices : (n, 3) float
    faces : (m, 3) int
    normals : (m, 3) float
        Output; zero for a degenerate triangle.
    offsets : (m,) float
        Output, in the units of ``vertices``.
    """
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        a0, a1, a2 = vertices[a, 0], vertices[a, 1], vertices[a, 2]
        e0, e1, e2 = vertices[b, 0] - a0, vertices[b, 1] - a1, vertices[b, 2] - a2
        w0, w1, w2 = vertices[c, 0] - a0, vertices[c, 1] - a1, vertices[c, 2] - a2
        n0 = e1 * w2 - e2 * w1
        n1 = e2 * w0 - e0 * w2
        n2 = e0 * w1 - e1 * w0
        norm = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        if norm > 0:
            inv = 1.0 / norm  # one division, not three: any unit normal with its own offset is exact
            n0, n1, n2 = n0 * inv, n1 * inv, n2 * inv
        normals[f, 0], normals[f, 1], normals[f, 2] = n0, n1, n2
        offsets[f] = n0 * a0 + n1 * a1 + n2 * a2


@jit
def scatter_face_sums(faces, face_sums, normals, out):
    """``out[v] += face_sums[f, j] * normals[f]`` for every corner ``j`` of every face ``f`` at vertex ``v``.

    Parameters
    ----------
    faces : (m, k) int
    face_sums : (m, k) float
    normals : (m, 3) float
    out : (n, 3) float
        Accumulated in place.
    """
    for f in range(faces.shape[0]):
        n0, n1, n2 = normals[f, 0], normals[f, 1], normals[f, 2]
        for j in range(faces.shape[1]):
            v, s = faces[f, j], face_sums[f, j]
            out[v, 0] += s * n0
            out[v, 1] += s * n1
            out[v, 2] += s * n2


@jit
def residual(values, k2, data, out):
    """``out = float32(values / k2) - data`` in float64, and ``0.5 |out|^2``.

    The projection is rounded to float32 first: that is what ``forward``
    returns, and the objective must be the misfit of that projection.

    Parameters
    ----------
    values : (n,) float
        Summed sub-ray values (flat).
    k2 : float
        Sub-rays per pixel.
    data : (n,) float32 or float
    out : (n,) float
        Output.
    """
    n = values.shape[0]
    f0 = f1 = f2 = f3 = 0.0  # four partial sums: one sum's add latency would bound the loop
    for i in range(0, n - n % 4, 4):
        r0 = np.float64(np.float32(values[i] / k2)) - np.float64(data[i])
        r1 = np.float64(np.float32(values[i + 1] / k2)) - np.float64(data[i + 1])
        r2 = np.float64(np.float32(values[i + 2] / k2)) - np.float64(data[i + 2])
        r3 = np.float64(np.float32(values[i + 3] / k2)) - np.float64(data[i + 3])
        out[i], out[i + 1], out[i + 2], out[i + 3] = r0, r1, r2, r3
        f0 += r0 * r0
        f1 += r1 * r1
        f2 += r2 * r2
        f3 += r3 * r3
    for i in range(n - n % 4, n):
        r0 = np.float64(np.float32(values[i] / k2)) - np.float64(data[i])
        out[i] = r0
        f0 += r0 * r0
    return 0.5 * ((f0 + f1) + (f2 + f3))
