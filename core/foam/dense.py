"""Dense wet-foam phantoms: bubbles pressed against each other, separated by thin films.

Real wet foams in the later stages of a 4D scan are dense (gas fraction
0.6-0.8): neighbouring bubbles are flattened against each other and separated
by liquid films thinner than a few voxels, with thicker Plateau borders where
three films meet. That is where voxel segmentation merges neighbours.

Construction (2D and 3D alike):

1. cell seeds at random positions, at least ``spacing`` apart (random
   sequential addition), with random weights: a power (Laguerre) diagram, so
   cells are polydisperse;
2. each bubble is its power cell shrunk by half a film plus the border
   radius ``rho``: the intersection of the half-spaces ``(x - s_i) . n_ij <=
   b_ij - film / 2 - rho`` of the neighbour bisectors and of the container
   walls less ``margin`` (scipy's ``HalfspaceIntersection``);
3. the shrunk convex cell ``Q`` is grown by ``rho`` (the Minkowski sum with a
   disc/ball), which rounds its corners into Plateau borders and keeps flat
   films of thickness exactly ``film`` between neighbours. The surface is
   sampled through its support points: for each unit direction ``u`` the
   point ``argmax_{q in Q} q . u + rho u``, with ``u`` on a circle (2D) or
   an icosphere (3D) whose connectivity becomes the mesh's.

The result is an exact, disjoint, convex-bubble foam whose films are
``film`` thick wherever two cells share a face.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linprog
from scipy.spatial import ConvexHull, HalfspaceIntersection

from bubsub.core.foam.checks import count, finite, frozen, nonneg, positive, rng_from_seed, size_vector, unit_icosphere
from bubsub.core.foam.containers import liquid_box, liquid_square
from bubsub.core.projection.mesh import Mesh, Polygon
from bubsub.core.foam.phantoms import FoamPhantom

__all__ = ["dense_foam2d", "dense_foam3d"]


def _seeds(rng, half, n, spacing, max_attempts):
    """Random points in ``[-half, half]`` at least ``spacing`` apart (random sequential addition)."""
    pts = []
    for _ in range(max_attempts * n):
        p = rng.uniform(-half, half)
        if all(np.linalg.norm(p - q) >= spacing for q in pts):
            pts.append(p)
            if len(pts) == n:
                return np.array(pts)
    raise ValueError(f"could place only {len(pts)} of {n} cell seeds {spacing:.3g} mm apart; "
                     "lower n_bubbles or spacing")


def _cell_vertices(i, seeds, weights, half_box, shrink):
    """Vertices of power cell ``i`` shrunk by ``shrink`` (mm), or None when nothing is left."""
    s, d = seeds[i], seeds.shape[1]
    rows = []
    for j in range(len(seeds)):
        if j == i:
            continue
        # power bisector: |x - s_i|^2 - w_i = |x - s_j|^2 - w_j, i.e. 2 (s_j - s_i) . x <= |s_j|^2 - |s_i|^2 - w_j + w_i
        a = 2 * (seeds[j] - s)
        norm = np.linalg.norm(a)
        b = seeds[j] @ seeds[j] - s @ s - weights[j] + weights[i]
        rows.append(np.append(a / norm, -(b / norm - shrink)))
    for k in range(d):  # walls of the container less the margin
        for sign in (1.0, -1.0):
            e = np.zeros(d)
            e[k] = sign
            rows.append(np.append(e, -(half_box[k] - shrink)))
    H = np.array(rows)
    # an interior point: the Chebyshev centre of the half-spaces (a small LP)

    A, b = H[:, :d], -H[:, d]
    res = linprog(np.append(np.zeros(d), -1.0), A_ub=np.hstack([A, np.linalg.norm(A, axis=1)[:, None]]), b_ub=b,
                  bounds=[(None, None)] * d + [(0, None)])
    if not res.success or res.x[-1] <= 1e-9:
        return None
    return HalfspaceIntersection(H, res.x[:d]).intersections


def _rounded(vertices, directions, rho):
    """Support points of ``conv(vertices) + rho * ball`` in the given unit directions."""
    best = np.argmax(directions @ vertices.T, axis=1)
    return vertices[best] + rho * directions


def _dense(seed, ndim, n, box, film, rho, spacing, polydispersity, margin, max_attempts, n_vertices, subdivisions):
    rng = rng_from_seed(seed)
    half = np.asarray(box) / 2.0
    volume = float(np.prod(box))
    if spacing is None:
        # about 0.8 x the mean cell diameter keeps random sequential addition easy
        spacing = 0.8 * (volume / n) ** (1.0 / ndim)
    seeds = _seeds(rng, half - margin, n, spacing, max_attempts)
    weights = (polydispersity * spacing) ** 2 * rng.uniform(-1, 1, n)
    if ndim == 2:
        t = 2 * np.pi * np.arange(n_vertices) / n_vertices
        dirs, faces = np.stack([np.cos(t), np.sin(t)], axis=1), None
    else:
        dirs, faces = unit_icosphere(subdivisions)
    bubbles, centres, radii = [], [], []
    for i in range(n):
        q = _cell_vertices(i, seeds, weights, half - margin, film / 2 + rho)
        if q is None:  # a cell smaller than its films: no gas left
            continue
        q = q[ConvexHull(q).vertices] if ndim == 2 else q
        v = _rounded(q, dirs, rho)
        b = Polygon(v, 0.0) if ndim == 2 else Mesh(v, faces, 0.0)
        bubbles.append(b)
        centres.append(b.centroid)
        radii.append(b.equivalent_radius)
    return bubbles, np.array(centres), np.array(radii)


def _phantom(bubbles, centres, radii, box, liquid_attenuation, gas_attenuation, seed):
    contrast = gas_attenuation - liquid_attenuation
    ndim = len(box)
    liquid = liquid_square(box[0], liquid_attenuation) if ndim == 2 else liquid_box(tuple(box), liquid_attenuation)
    return FoamPhantom(liquid=liquid, bubbles=tuple(b.with_attenuation(contrast) for b in bubbles), size=tuple(box),
                       liquid_attenuation=liquid_attenuation, gas_attenuation=gas_attenuation,
                       centres=frozen(centres), radii=frozen(radii), seed=seed)


def dense_foam2d(seed, n_bubbles=40, size=10.0, film=0.08, border=0.3, spacing=None, polydispersity=0.3,
                 margin=0.25, liquid_attenuation=0.1, gas_attenuation=0.0, n_vertices=128, max_attempts=2000):
    """Dense 2D wet foam: power-diagram cells shrunk by a film and rounded by Plateau borders.

    Parameters
    ----------
    seed : int
    n_bubbles : int
        Cell seeds (cells left without gas are skipped, so a few fewer bubbles
        may result).
    size : float
        Side of the liquid square, mm.
    film : float
        Liquid film thickness between neighbouring bubbles, mm.
    border : float
        Radius of the rounded cell corners (Plateau borders), mm.
    spacing : float, optional
        Least distance between cell seeds, mm (default 0.8 x mean cell size).
    polydispersity : float
        Power-diagram weights uniform in ``+-(polydispersity x spacing)^2``.
    margin : float
        Liquid between the foam and the container walls, mm.
    n_vertices : int
        Outline directions per bubble (corner arcs and flat films).

    Returns
    -------
    FoamPhantom
        Gas fraction about 0.7 with the defaults (:attr:`FoamPhantom.gas_fraction`).
    """
    n = count("n_bubbles", n_bubbles)
    side = positive("size", size)
    box = (side, side)
    bubbles, centres, radii = _dense(seed, 2, n, box, nonneg("film", film), nonneg("border", border), spacing,
                                     nonneg("polydispersity", polydispersity), nonneg("margin", margin),
                                     count("max_attempts", max_attempts), count("n_vertices", n_vertices, minimum=8), None)
    return _phantom(bubbles, centres, radii, box, finite("liquid_attenuation", liquid_attenuation),
                    finite("gas_attenuation", gas_attenuation), seed)


def dense_foam3d(seed, n_bubbles=40, size=(8.0, 8.0, 4.0), film=0.08, border=0.2, spacing=None, polydispersity=0.3,
                 margin=0.2, liquid_attenuation=0.1, gas_attenuation=0.0, subdivisions=3, max_attempts=2000):
    """Dense 3D wet foam: power-diagram cells shrunk by a film and rounded by Plateau borders.

    Parameters as :func:`dense_foam2d`; ``size`` is the box ``(x, y, z)``, mm;
    ``subdivisions`` of the icosphere of directions (3: 642 vertices per bubble).

    Returns
    -------
    FoamPhantom
    """
    n = count("n_bubbles", n_bubbles)
    box = size_vector(size, 3)
    bubbles, centres, radii = _dense(seed, 3, n, box, nonneg("film", film), nonneg("border", border), spacing,
                                     nonneg("polydispersity", polydispersity), nonneg("margin", margin),
                                     count("max_attempts", max_attempts), None, count("subdivisions", subdivisions, minimum=0))
    return _phantom(bubbles, centres, radii, box, finite("liquid_attenuation", liquid_attenuation),
                    finite("gas_attenuation", gas_attenuation), seed)
