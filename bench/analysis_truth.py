"""The analytic truth of ``python -m bubsub.bench analysis``: ellipsoids, subdivided ellipsoids, a column's truth.

* :func:`ellipsoid_area` (Legendre's elliptic integrals) and :func:`ellipsoid_gap`
  (the distance of two ellipsoids from their support functions), no mesh involved;
* :func:`subdivided_ellipsoid`: a Loop subdivision surface fitted to an ellipsoid,
  as bubsub fits its bubbles, and :func:`shape_table`, the analysis' errors on
  such surfaces (``--shapes``);
* :func:`load_column` and :func:`column_truth`: a column simulation folder's
  ellipsoids and what they give for each quantity the benchmark scores.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.optimize import minimize
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from scipy.special import ellipeinc, ellipkinc

from bubsub.core.analysis.contacts import find_contacts
from bubsub.core.analysis.shape import bubble_shape, strain_from_axes
from bubsub.core.foam.ellipsoids import shape_matrices
from bubsub.core.projection.mesh import Mesh
from bubsub.core.projection.subdivision import icosphere, loop_subdivision

__all__ = ["ellipsoid_area", "ellipsoid_gap", "subdivided_ellipsoid", "shape_table", "load_column", "column_truth"]

def ellipsoid_area(axes):
    """Exact surface area of an ellipsoid of semi-axes ``axes`` (Legendre's form), mm^2."""
    a, b, c = sorted((float(x) for x in axes), reverse=True)
    if a - c < 1e-12 * a:
        return 4 * np.pi * a * a
    phi = np.arccos(c / a)
    m = a * a * (b * b - c * c) / (b * b * (a * a - c * c))
    return float(2 * np.pi * c * c + 2 * np.pi * a * b / np.sin(phi) * (
        ellipeinc(phi, m) * np.sin(phi) ** 2 + ellipkinc(phi, m) * np.cos(phi) ** 2))


def ellipsoid_gap(c1, S1, c2, S2):
    """Distance between two disjoint ellipsoids and the middle of their closest points, without any mesh.

    The distance between disjoint convex bodies is the widest separation of two
    parallel support planes, ``max over |n| <= 1 of n.(c2 - c1) - h1(n) - h2(n)`` with
    the support function ``h(n) = sqrt(n^T S n)`` of an ellipsoid of shape matrix
    ``S`` (a concave maximisation, solved by SLSQP).

    Returns
    -------
    gap : float
        mm (<= 0 when they overlap).
    point : (3,) float
        Midpoint of the two support points along the best ``n``.
    """
    c1, c2 = np.asarray(c1, dtype=float), np.asarray(c2, dtype=float)
    d = c2 - c1

    def minus(n):
        return -(n @ d - np.sqrt(n @ S1 @ n + 1e-300) - np.sqrt(n @ S2 @ n + 1e-300))

    res = minimize(minus, d / np.linalg.norm(d), method="SLSQP", options={"ftol": 1e-13, "maxiter": 200},
                   constraints=[{"type": "ineq", "fun": lambda n: 1.0 - n @ n}])
    n = res.x / max(np.linalg.norm(res.x), 1e-300)
    p1 = c1 + S1 @ n / np.sqrt(n @ S1 @ n)
    p2 = c2 - S2 @ n / np.sqrt(n @ S2 @ n)
    return float(-res.fun), 0.5 * (p1 + p2)


def subdivided_ellipsoid(axes, rotation, centre, control=1, levels=2):
    """A Loop subdivision surface fitted (least squares) to an ellipsoid, as bubsub fits its bubbles.

    The control mesh is an icosphere of ``control`` subdivisions (1: 42 vertices,
    bubsub's default); its ``levels``-times subdivided vertices are asked to lie
    on the ellipsoid (semi-axes ``axes`` along the columns of ``rotation``, about
    ``centre``) at the images of their directions.

    Returns
    -------
    Mesh
        The fine (subdivided) mesh.
    """
    v, f = icosphere(control)
    S, fine_faces = loop_subdivision(f, len(v), levels)
    u = S @ v
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    target = np.asarray(centre) + (u * np.asarray(axes)) @ np.asarray(rotation).T
    x = np.linalg.lstsq(S.toarray(), target, rcond=None)[0]
    return Mesh(S @ x, fine_faces)


def shape_table(pairs=20, seed=1):
    """Print the analysis' errors on analytic shapes (the ``--shapes`` tables of the module docstring).

    Parameters
    ----------
    pairs : int
        Ellipsoid pairs of the gap table, at support-plane distances spread over 5-50 um.
    seed : int
    """

    axes = np.array([0.6, 0.45, 0.3])
    rot = Rotation.from_euler("zyx", [30, 50, -20], degrees=True).as_matrix()
    volume, area = 4 / 3 * np.pi * axes.prod(), ellipsoid_area(axes)
    sph = np.pi ** (1 / 3) * (6 * volume) ** (2 / 3) / area
    _, vm, _ = strain_from_axes(axes)
    print(f"Loop subdivision surfaces fitted to an ellipsoid of semi-axes {axes.tolist()} mm\n\n"
          "| fine vertices | volume error (%) | area error (%) | sphericity error | semi-axis error (%) | strain error |\n"
          "|---|---|---|---|---|---|")
    for control, levels in ((1, 2), (1, 3), (2, 2), (2, 3)):
        mesh = subdivided_ellipsoid(axes, rot, np.zeros(3), control, levels)
        s = bubble_shape(mesh)
        semi = np.array([s[f"semi_axis_{i}_mm"] for i in (1, 2, 3)])
        worst = int(np.argmax(np.abs(semi / axes - 1)))
        print(f"| {len(mesh.vertices)} ({10 * 4 ** control + 2} control, {levels} levels) | "
              f"{100 * (s['volume_mm3'] / volume - 1):.3f} | {100 * (s['surface_area_mm2'] / area - 1):.3f} | "
              f"{s['sphericity'] - sph:.5f} | {100 * (semi[worst] / axes[worst] - 1):.3f} | "
              f"{s['strain_von_mises'] - vm:.5f} |", flush=True)
    rng = np.random.default_rng(seed)
    errors = {2: [], 3: []}
    for g in np.linspace(0.005, 0.05, pairs):
        ax1, ax2 = 0.3 + 0.3 * rng.random(3), 0.3 + 0.3 * rng.random(3)
        r1, r2 = Rotation.random(2, random_state=rng).as_matrix()
        s1, s2 = shape_matrices(np.stack([ax1, ax2]), np.stack([r1, r2]))
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        c1 = np.zeros(3)
        p1 = c1 + s1 @ n / np.sqrt(n @ s1 @ n)
        c2 = p1 + g * n + s2 @ n / np.sqrt(n @ s2 @ n)  # parallel support planes g apart along n
        for levels in errors:
            meshes = [subdivided_ellipsoid(ax1, r1, c1, 1, levels), subdivided_ellipsoid(ax2, r2, c2, 1, levels)]
            c = find_contacts(meshes, 0.1)
            errors[levels].append(c.gap[0] - g if len(c) else np.nan)
    print(f"\nGap between two such meshes of rotated ellipsoids (semi-axes 0.3-0.6 mm) {pairs} times, their support "
          "planes 5-50 um apart\n\n| fine vertices | mean gap error (um) | largest gap error (um) |\n|---|---|---|")
    for levels, e in errors.items():
        e = 1000 * np.array(e)
        print(f"| {10 * 4 ** (levels + 1) + 2} (42 control, {levels} levels) | {np.mean(e):.2f} | "
              f"{e[np.argmax(np.abs(e))]:.2f} |", flush=True)


def load_column(folder):
    """The analytic truth of a column simulation folder (:func:`bubsub.core.foam.column.write_column`).

    Returns
    -------
    dict
        ``centres`` (n, 3), ``axes`` (n, 3, in the rotation's column order), ``rotations`` (n, 3, 3), ``cut``
        (n,) bool (crossing the detector's top or bottom), ``volume_in_fov`` (n,), ``radius`` (the liquid
        cylinder's), ``fov_radius``, ``half_height``, ``grid_shape``, ``grid_extent``, ``contrast``.
    """
    import csv
    import json

    folder = Path(folder)
    meta = json.loads((folder / "phantom.json").read_text())
    if meta.get("phantom") != "column":
        raise ValueError(f"{folder} is not a column simulation (phantom.json says {meta.get('phantom')!r})")
    with open(folder / "truth.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    col = meta["column"]

    def get(names):
        return np.array([[float(r[n]) for n in names] for r in rows])

    return {"centres": get([f"centre_{a}_mm" for a in "xyz"]), "axes": get([f"semi_axis_{k}_mm" for k in (1, 2, 3)]),
            "rotations": get([f"rotation_{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3)]).reshape(-1, 3, 3),
            "cut": (get(["cut_top"])[:, 0] + get(["cut_bottom"])[:, 0]) > 0,
            "volume_in_fov": get(["volume_in_fov_mm3"])[:, 0], "radius": float(col["radius_mm"]),
            "fov_radius": float(col["fov_radius_mm"]), "half_height": float(col["fov_half_height_mm"]),
            "grid_shape": tuple(meta["grid_shape"]), "grid_extent": tuple(meta["grid_extent"]),
            "contrast": float(meta["bubble_contrast"])}


def column_truth(col, gap):
    """Analytic truth of a column's bubbles (:func:`load_column`) for a contact gap.

    Returns
    -------
    dict
        Arrays over the bubbles: ``centre``, ``axes`` (descending), ``volume``, ``radius``, ``sphericity``,
        ``strain_vm``, ``cut`` (bool), ``volume_in_fov``; ``contacts``: ``{(i, j): point}`` of the pairs
        closer than ``gap`` whose contact point lies in the rows; ``gaps``: the distance of every pair
        examined; ``liquid_fraction`` of the liquid cylinder within the rows.
    """

    centre, axes = col["centres"], col["axes"]
    shapes = shape_matrices(axes, col["rotations"])
    axes_sorted = -np.sort(-axes, axis=1)
    volume = 4 / 3 * np.pi * axes.prod(axis=1)
    area = np.array([ellipsoid_area(a) for a in axes])
    _, vm, _ = strain_from_axes(axes_sorted)
    h = col["half_height"]
    contacts, gaps = {}, {}
    reach = axes.max(axis=1)
    for i, j in sorted(map(tuple, cKDTree(centre).query_pairs(2 * reach.max() + gap, output_type="ndarray"))):
        if np.linalg.norm(centre[i] - centre[j]) >= reach[i] + reach[j] + gap:
            continue
        g, point = ellipsoid_gap(centre[i], shapes[i], centre[j], shapes[j])
        gaps[(i, j)] = g
        if g < gap and abs(point[2]) <= h:
            contacts[(i, j)] = point
    gas = float(col["volume_in_fov"].sum())
    return {"centre": centre, "axes": axes_sorted, "volume": volume, "radius": np.cbrt(3 * volume / (4 * np.pi)),
            "sphericity": np.pi ** (1 / 3) * (6 * volume) ** (2 / 3) / area, "strain_vm": vm, "cut": col["cut"],
            "volume_in_fov": col["volume_in_fov"], "contacts": contacts, "gaps": gaps,
            "liquid_fraction": 1 - gas / (np.pi * col["radius"] ** 2 * 2 * h)}
