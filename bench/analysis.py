"""Benchmark "analysis": ``bubsub analyse`` against FoamQuant's voxel route, both against the truth; its cost.

``python -m bubsub.bench analysis [--bubbles 150] [--seed 0] [--simulation DIR] [--reconstruction DIR]
[--keep DIR] [--contact-gap MM] [--voxel-method cgls] [--cost-bubbles 150 600] [--repeats 3] [--no-foamquant]
[--no-reconstruction] [--cost-only] [--shapes]``

The foam is a simulated synchrotron column (:mod:`bubsub.core.foam.column`:
rotated polydisperse ellipsoids in a liquid cylinder, gas fraction 0.4,
parallel beam, 40 projections of 256 x 768 pixels of 12 um, I0 = 1e4), whose
truth is analytic: each ellipsoid's volume, area (Legendre's elliptic
integrals), sphericity, semi-axes and internal strain, the exact volume
inside the detector's rows, and the surface distance of every pair (the
widest separation of parallel support planes, a concave maximisation;
:func:`~bubsub.bench.analysis_truth.ellipsoid_gap`). The same scan is measured by

* **bubsub**: ``bubsub reconstruct`` with its defaults (or the folder given by
  ``--reconstruction``; left out with ``--no-reconstruction``), then
  :func:`bubsub.clients.analysis.analyse`;
* **FoamQuant, voxel route**: a voxel reconstruction of the same scan
  (``--voxel-method``, default CGLS, 15 iterations, on the grid of two
  detector pixels the column's evaluation uses), FoamQuant's
  ``PhaseSegmentation`` (global Otsu), ``BubbleSegmentation`` (watershed of the
  smoothed distance map, seeds at least half the median radius apart) and
  ``RegionProp``; labels touching the top or bottom slice are the cut bubbles
  (FoamQuant's ``RemoveEdgeBubble``); two labels are in contact when voxels of
  both lie within the contact gap plus one voxel of each other (FoamQuant's
  contacts, spam's ``labelledContacts``, take touching labels: a gap of about one
  voxel);
* **FoamQuant on the truth voxelised**: the same segmentation and ``RegionProp``
  on the exact voxelisation of the truth (its best case: a perfect voxel
  reconstruction at that voxel size);
* **bubsub on the truth meshes**: :func:`bubsub.core.analysis.analyse_meshes` on
  642-vertex meshes of the true ellipsoids (what the analysis itself adds).

Errors are medians over the truth bubbles not cut by the field of view that a
method finds (a measured centroid within half the equivalent radius of the
true centre, one to one) and does not flag as cut. Contacts are scored on the
pairs whose contact point lies in the field of view: precision and recall of
the measured pairs (through the matching) against the true pairs closer than
the contact gap, then the same among the bubbles the method found (measured
pairs of two matched bubbles against true pairs of two found ones), which
leaves out what the missed and spurious bubbles cost. The cost table times :func:`analyse_meshes` on the truth
meshes of columns of ``--cost-bubbles`` bubbles (median of ``--repeats``).
``--shapes`` prints the analysis' own error on analytic shapes instead: Loop
subdivision surfaces fitted to an ellipsoid at four resolutions (volume,
area, sphericity, semi-axes, strain against their closed forms), and the gap
between two such meshes of rotated ellipsoids whose support planes are a
known distance apart (:func:`~bubsub.bench.analysis_truth.shape_table`).

FoamQuant is optional (``pip install 'bubsub[foamquant]'``, or ``pip install
--no-deps foamquant``: the functions used need only numpy, scipy and
scikit-image); without it the FoamQuant columns are left out.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import itertools
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from bubsub.bench.analysis_truth import column_truth, load_column, shape_table
from bubsub.core.projection.mesh import equivalent_radius
from bubsub.clients.analysis import analyse, default_contact_gap, read_reconstruction
from bubsub.clients.pipeline.results.outputs import write_outputs
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, reconstruct
from bubsub.core.analysis.regions import Domain
from bubsub.core.analysis.snapshot import analyse_meshes
from bubsub.core.foam.column import column_phantom, simulate_column, write_column
from bubsub.core.foam.ellipsoids import ellipsoid_labels, ellipsoid_mesh
from bubsub.core.io.scanfile import read_scan
from bubsub.core.projection.masks import pixel_centres
from bubsub.core.voxel.reconstruct3d import reconstruct_3d

__all__ = ["score", "foamquant_route", "label_contacts", "compare", "cost_table", "main"]


def _match(centroids, truth):
    """Measured index -> truth index: nearest centres within half the true equivalent radius, one to one."""
    if not len(centroids):
        return {}
    d, k = cKDTree(np.asarray(centroids)).query(truth["centre"], k=1)
    pairs = sorted((float(dd), int(t), int(m)) for t, (dd, m) in enumerate(zip(d, k))
                   if dd < 0.5 * truth["radius"][t])
    out, used = {}, set()
    for _, t, m in pairs:
        if m not in used and t not in out.values():
            out[m] = t
            used.add(m)
    return out


def score(m, truth, fov_half_height):
    """Errors of one method against the truth (see the module docstring).

    Parameters
    ----------
    m : dict
        ``centroid`` (n, 3), ``volume``, ``sphericity``, ``sphericity_ellipsoid``, ``axes`` (n, 3, descending),
        ``strain_vm``, ``cut`` (n,) bool, ``pairs`` (k, 2) indices into the method's bubbles, ``points`` (k, 3),
        ``liquid_fraction``, ``seconds``.
    """
    match = _match(m["centroid"], truth)
    whole = [(i, t) for i, t in match.items() if not truth["cut"][t] and not m["cut"][i]]
    n_whole = int((~truth["cut"]).sum())
    i, t = (np.array([p[k] for p in whole], dtype=int) for k in (0, 1)) if whole else (np.zeros(0, int),) * 2

    def med(x):
        return float(np.median(np.abs(x))) if len(x) else float("nan")

    found = set()
    for (a, b), p in zip(np.asarray(m["pairs"]).reshape(-1, 2), np.asarray(m["points"]).reshape(-1, 3)):
        if abs(p[2]) > fov_half_height:
            continue
        ta, tb = match.get(int(a), -1 - int(a)), match.get(int(b), -1 - int(b))  # unmatched: never a true pair
        found.add((min(ta, tb), max(ta, tb)))
    true = set(truth["contacts"])
    hit = len(found & true)
    # the same among the bubbles the method found: what its surfaces get wrong, apart from bubbles it missed
    kept = set(match.values())
    found_m = {p for p in found if p[0] >= 0}
    true_m = {p for p in true if p[0] in kept and p[1] in kept}
    hit_m = len(found_m & true_m)
    coord_m = np.bincount(np.asarray(m["pairs"], dtype=int).ravel(), minlength=len(m["centroid"]))
    coord_t = np.bincount(np.array(list(true), dtype=int).ravel(), minlength=len(truth["centre"])) if true else \
        np.zeros(len(truth["centre"]), int)
    return {
        "found": f"{len(whole)} / {n_whole}",
        "spurious": len(m["centroid"]) - len(match),
        "volume": 100 * med(m["volume"][i] / truth["volume"][t] - 1),
        "radius": 1000 * med(equivalent_radius(m["volume"][i], 3) - truth["radius"][t]),
        "sphericity": med(m["sphericity"][i] - truth["sphericity"][t]),
        "sphericity_ellipsoid": med(m["sphericity_ellipsoid"][i] - truth["sphericity"][t]),
        "axes": 100 * med((m["axes"][i] / truth["axes"][t] - 1).ravel()),
        "strain": med(m["strain_vm"][i] - truth["strain_vm"][t]),
        "precision": hit / len(found) if found else float("nan"),
        "recall": hit / len(true) if true else float("nan"),
        "precision_found": hit_m / len(found_m) if found_m else float("nan"),
        "recall_found": hit_m / len(true_m) if true_m else float("nan"),
        "coordination": float(np.mean(np.abs(coord_m[i] - coord_t[t]))) if len(i) else float("nan"),
        "liquid_fraction": abs(m["liquid_fraction"] - truth["liquid_fraction"]),
        "seconds": m["seconds"],
    }


def _from_snapshot(snap, seconds):
    """A method's measurements from a :class:`~bubsub.core.analysis.snapshot.Snapshot`-like table set."""
    def col(name, rows):
        return np.array([np.nan if r[name] == "" else float(r[name]) for r in rows])

    b = snap["bubbles"]
    index = {int(r["id"]): k for k, r in enumerate(b)}
    pairs = [(index[int(r["id_a"])], index[int(r["id_b"])]) for r in snap["contacts"]]
    return {"centroid": np.stack([col(f"centroid_{a}_mm", b) for a in "xyz"], axis=1), "volume": col("volume_mm3", b),
            "sphericity": col("sphericity", b), "sphericity_ellipsoid": col("sphericity_ellipsoid", b),
            "axes": np.stack([col(f"semi_axis_{k}_mm", b) for k in (1, 2, 3)], 1),
            "strain_vm": col("strain_von_mises", b), "cut": col("truncated", b) == 1,
            "pairs": np.array(pairs, dtype=int).reshape(-1, 2),
            "points": np.array([[float(r[f"contact_{a}_mm"]) for a in "xyz"] for r in snap["contacts"]]).reshape(-1, 3),
            "liquid_fraction": snap["liquid_fraction"], "seconds": seconds}


def label_contacts(labels, reach):
    """Pairs of labels with voxels of both within ``reach`` voxels (centre to centre) of each other.

    Returns
    -------
    (k, 2) int
        Label pairs ``(a, b)``, ``a < b``.
    """
    r = int(np.floor(reach))
    offsets = [o for o in itertools.product(range(-r, r + 1), repeat=3) if o > (0, 0, 0) and np.dot(o, o) <= reach ** 2]
    n = int(labels.max()) + 1
    found = set()
    for o in offsets:
        a = labels[tuple(slice(max(0, -k), labels.shape[d] - max(0, k)) for d, k in enumerate(o))]
        b = labels[tuple(slice(max(0, k), labels.shape[d] - max(0, -k)) for d, k in enumerate(o))]
        sel = (a > 0) & (b > 0) & (a != b)
        if sel.any():
            x, y = a[sel].astype(np.int64), b[sel].astype(np.int64)
            found.update(np.unique(np.minimum(x, y) * n + np.maximum(x, y)).tolist())
    return np.array(sorted((k // n, k % n) for k in found), dtype=int).reshape(-1, 2)


def foamquant_route(binary, extent, voxel, min_distance, gap, mask):
    """FoamQuant's bubble segmentation and RegionProp on a binary gas image (1 = gas), in mm.

    Parameters
    ----------
    binary : (z, y, x) uint8
    extent : (xmin, xmax, ymin, ymax, zmin, zmax)
    voxel : float, mm
    min_distance : int
        Least distance between watershed seeds, voxels.
    gap : float
        Contact gap, mm.
    mask : (z, y, x) bool
        The sample (for the liquid fraction).
    """
    from foamquant.FromLabelled import RegionProp
    from foamquant.Process import BubbleSegmentation

    t = time.perf_counter()
    labels = np.asarray(BubbleSegmentation(binary, SigSeeds=1, SigWatershed=1, watershed_line=False,
                                           esti_min_dist=int(min_distance)), dtype=np.int32)
    with contextlib.redirect_stdout(io.StringIO()) as said:  # a line per degenerate label, with every volume so far
        prop = RegionProp(labels)
    flat = said.getvalue().count("negative shape value")
    if flat:
        print(f"FoamQuant RegionProp: {flat} labels without an ellipsoid (their shape columns are left empty)")
    lab, cen, vol, sph = np.array(prop[0]), np.array(prop[1], dtype=float).reshape(-1, 3), np.array(prop[2]), \
        np.array(prop[5], dtype=float)
    axes = np.stack([np.array(prop[k], dtype=float) for k in (9, 8, 7)], axis=1) * voxel  # descending
    xmin, _, _, ymax, zmin, _ = extent
    centroid = np.stack([xmin + (cen[:, 2] + 0.5) * voxel, ymax - (cen[:, 1] + 0.5) * voxel,
                         zmin + (cen[:, 0] + 0.5) * voxel], axis=1)
    edge = set(np.unique(labels[0]).tolist()) | set(np.unique(labels[-1]).tolist())  # FoamQuant's RemoveEdgeBubble
    pairs_lab = label_contacts(labels, gap / voxel + 1.0)
    index = {int(v): k for k, v in enumerate(lab)}
    pairs = np.array([(index[a], index[b]) for a, b in pairs_lab if a in index and b in index], dtype=int).reshape(-1, 2)
    points = 0.5 * (centroid[pairs[:, 0]] + centroid[pairs[:, 1]]) if len(pairs) else np.zeros((0, 3))
    strain = np.array(prop[22], dtype=float)
    seconds = time.perf_counter() - t
    sph = np.where(sph > 0, sph, np.nan)  # RegionProp's only sphericity is its ellipsoid's
    return {"centroid": centroid, "volume": vol * voxel ** 3, "sphericity": sph, "sphericity_ellipsoid": sph,
            "axes": np.where(axes > 0, axes, np.nan), "strain_vm": np.where(strain >= 0, strain, np.nan),
            "cut": np.array([v in edge for v in lab]), "pairs": pairs, "points": points,
            "liquid_fraction": 1 - float(binary[mask].mean()), "seconds": seconds}


def _cylinder_mask(shape, extent, radius):
    _, y, x = pixel_centres(shape, extent)
    inside = np.hypot(x[None, :], y[:, None]) <= radius
    return np.broadcast_to(inside, shape)


_ROWS = (("found", "bubbles found whole (of the whole truth bubbles)", "{}"),
         ("spurious", "measured bubbles matching no truth bubble", "{}"),
         ("volume", "median volume error (%)", "{:.2f}"),
         ("radius", "median equivalent-radius error (um)", "{:.2f}"),
         ("sphericity", "median sphericity error (bubsub: its surface; FoamQuant: its ellipsoid)", "{:.5f}"),
         ("sphericity_ellipsoid", "median sphericity error, ellipsoid of the shape tensor (FoamQuant's)", "{:.5f}"),
         ("axes", "median semi-axis error, shape tensor (%)", "{:.2f}"),
         ("strain", "median internal-strain error (von Mises)", "{:.4f}"),
         ("precision", "contacts: precision", "{:.3f}"),
         ("recall", "contacts: recall", "{:.3f}"),
         ("precision_found", "contacts between found bubbles: precision", "{:.3f}"),
         ("recall_found", "contacts between found bubbles: recall", "{:.3f}"),
         ("coordination", "mean coordination error", "{:.2f}"),
         ("liquid_fraction", "liquid fraction error", "{:.4f}"),
         ("seconds", "analysis seconds (after the reconstruction)", "{:.1f}"))


def _print_table(results):
    names = list(results)
    print("| quantity | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    for key, label, fmt in _ROWS:
        cells = [fmt.format(results[n][key]) if not (isinstance(results[n][key], float) and np.isnan(results[n][key]))
                 else "-" for n in names]
        print(f"| {label} | " + " | ".join(cells) + " |", flush=True)


def _folders(a):
    """The column's simulation folder and a reconstruct folder of its scan (made when not given)."""
    import tempfile


    if a.simulation and a.reconstruction:
        return Path(a.simulation), Path(a.reconstruction), None
    work = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="bubsub-bench-analysis-"))
    sim = Path(a.simulation) if a.simulation else work / "simulation"
    if not a.simulation:
        ph = column_phantom(a.bubbles, seed=a.seed)
        write_column(sim, ph, simulate_column(ph))
    if a.reconstruction or a.no_reconstruction:
        return sim, Path(a.reconstruction) if a.reconstruction else None, None
    t = time.perf_counter()
    rec = reconstruct(read_scan(sim / "scan.h5"), ReconstructionSettings(progress=False))
    write_outputs(work / "reconstruction", rec)
    return sim, work / "reconstruction", time.perf_counter() - t


def cost_table(sizes, repeats, seed):
    """Seconds of :func:`analyse_meshes` on the 642-vertex truth meshes of columns of ``sizes`` bubbles."""
    print("\n| bubbles | vertices | contacts | shape s | contacts s | regions s | total s (median of "
          f"{repeats}) |\n|---|---|---|---|---|---|---|", flush=True)
    for n in sizes:
        ph = column_phantom(n, seed=seed)
        meshes = ph.truth_meshes(3)
        fov = (ph.radius, ph.fov_half_height)
        gap = 2 * ph.fov_radius / 160
        runs = []
        for _ in range(repeats):
            t = time.perf_counter()
            snap = analyse_meshes(meshes, contact_gap=gap, field_of_view=fov)
            runs.append((time.perf_counter() - t, snap.summary["seconds"], snap.summary["contacts"]))
        k = int(np.argsort([r[0] for r in runs])[len(runs) // 2])
        total, parts, contacts = runs[k]
        print(f"| {len(meshes)} | {sum(len(m.vertices) for m in meshes)} | {contacts} | {parts['shape']:.2f} | "
              f"{parts['contacts']:.2f} | {parts['regions']:.2f} | {total:.2f} |", flush=True)


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m bubsub.bench analysis", description=__doc__.split("\n\n")[0])
    p.add_argument("--bubbles", type=int, default=150, help="bubbles in the column's rows (default 150)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--simulation", metavar="DIR", help="a column simulation folder (bubsub simulate --phantom column; "
                                                        "default: simulate --bubbles)")
    p.add_argument("--reconstruction", metavar="DIR", help="a bubsub reconstruct folder of that scan (skips the "
                                                            "reconstruction)")
    p.add_argument("--keep", metavar="DIR", help="write the simulation and reconstruction here (for --simulation "
                                                  "and --reconstruction later; default a temporary folder)")
    p.add_argument("--contact-gap", type=float, help="mm (default: bubsub's default, one preview voxel)")
    p.add_argument("--voxel-method", default="cgls", help="voxel reconstruction of the voxel route (default cgls)")
    p.add_argument("--cost-bubbles", type=int, nargs="*", default=[150, 600])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--no-foamquant", action="store_true", help="leave the FoamQuant columns out")
    p.add_argument("--no-reconstruction", action="store_true",
                   help="leave bubsub's reconstruction of the scan out (the truth and FoamQuant columns only)")
    p.add_argument("--cost-only", action="store_true", help="only the cost table")
    p.add_argument("--shapes", action="store_true", help="only the analysis' errors on analytic shapes (no column)")
    a = p.parse_args(argv)
    if a.shapes:
        shape_table()
        return 0
    if not a.cost_only:
        compare(a)
    if a.cost_bubbles:
        cost_table(a.cost_bubbles, a.repeats, a.seed)
    return 0


def compare(a):
    sim, folder, rec_seconds = _folders(a)
    col = load_column(sim)
    report = read_reconstruction(folder).report if folder else {"field_of_view_mm": {"radius": col["fov_radius"]}}
    gap = a.contact_gap or default_contact_gap(report)
    t = time.perf_counter()
    truth = column_truth(col, gap)
    h = col["half_height"]
    print(f"column {sim}: {len(col['centres'])} bubbles in the rows ({int(col['cut'].sum())} cut), liquid fraction "
          f"{truth['liquid_fraction']:.4f}; contact gap {gap:.4f} mm: {len(truth['contacts'])} true contacts among "
          f"{len(truth['gaps'])} close pairs (truth {time.perf_counter() - t:.0f} s); bubsub reconstruction "
          + ("left out" if folder is None else f"{rec_seconds:.0f} s, in {folder}" if rec_seconds is not None
             else f"read from {folder}"), flush=True)
    results = {}
    if folder is not None:
        t = time.perf_counter()
        ours = analyse(folder, contact_gap=gap, radius=col["radius"])
        results["bubsub (meshes of the scan)"] = score(
            _from_snapshot({**ours.tables, "liquid_fraction": ours.summary["liquid_fraction"]},
                           time.perf_counter() - t), truth, h)
    if not a.no_foamquant:
        try:
            import foamquant  # noqa: F401
        except ImportError:
            print("FoamQuant is not installed (pip install 'bubsub[foamquant]'): its columns are left out")
        else:
            results.update(_foamquant_columns(a, sim, col, truth, gap))
    first = ellipsoid_mesh(col["centres"][0], col["axes"][0], col["rotations"][0], col["contrast"], 3)
    meshes = [first] + [ellipsoid_mesh(c, x, r, col["contrast"], 3, template=first)
                        for c, x, r in zip(col["centres"][1:], col["axes"][1:], col["rotations"][1:])]
    t = time.perf_counter()
    snap = analyse_meshes(meshes, contact_gap=gap, field_of_view=(col["fov_radius"], h), truncated=col["cut"].astype(int),
                          domain=Domain.field_of_view(col["radius"], h))
    results["bubsub (truth meshes)"] = score(
        _from_snapshot({"bubbles": snap.bubbles, "contacts": snap.contacts,
                        "liquid_fraction": snap.summary["liquid_fraction"]}, time.perf_counter() - t), truth, h)
    _print_table(results)


def _foamquant_columns(a, sim, col, truth, gap):
    from foamquant.Process import PhaseSegmentation


    shape, extent = col["grid_shape"], col["grid_extent"]
    voxel = (extent[1] - extent[0]) / shape[2]
    mask = _cylinder_mask(shape, extent, col["radius"])
    seeds = max(1, int(round(0.5 * float(np.median(truth["radius"])) / voxel)))
    scan = read_scan(sim / "scan.h5")
    out = {}
    t = time.perf_counter()
    image = reconstruct_3d(a.voxel_method, np.sign(scan.bubble_contrast) * scan.bubble_data, scan.geometry, shape,
                           extent)
    print(f"voxel route: {a.voxel_method} on {shape} voxels of {voxel * 1000:.0f} um, {time.perf_counter() - t:.0f} s",
          flush=True)
    t = time.perf_counter()
    binary = np.asarray(PhaseSegmentation(-image, method="ostu_global"), dtype=np.uint8) * mask
    m = foamquant_route(binary, extent, voxel, seeds, gap, mask)
    m["seconds"] = time.perf_counter() - t  # with the phase segmentation
    out[f"FoamQuant ({a.voxel_method.upper()} voxels of the scan)"] = score(m, truth, col["half_height"])
    ideal = (ellipsoid_labels(col["centres"], col["axes"], col["rotations"], shape, extent) > 0).astype(np.uint8)
    out["FoamQuant (truth voxelised)"] = score(foamquant_route(ideal, extent, voxel, seeds, gap, mask), truth,
                                               col["half_height"])
    return out
