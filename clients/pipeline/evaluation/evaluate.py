"""Scoring a reconstruction folder against a simulation folder: DDI, per-bubble matches, size errors, a picture.

:func:`evaluate_dir` takes a ``bubsub reconstruct`` folder, a ``subscan_NNNN``
folder of ``bubsub reconstruct4d`` or a whole ``reconstruct4d`` folder, and
the ``bubsub simulate`` folder of its scan (static or dynamic: a 4D
simulation holds one truth per subscan). The truth and the reconstruction
are rasterised on the simulation's grid (``phantom.json``'s ``grid_shape``
/ ``grid_extent``), counting only its voxels inside the field of view (the
part of the sample the data see: the reconstruction's ``report.json``
``field_of_view_mm``, else a column simulation's; the whole grid when
neither gives one). On those voxels:

* the DDI, ``1 - 2 |R n T| / (|R| + |T|)`` of the reconstructed and true
  gas;
* the bubble-by-bubble matching of :func:`bubsub.core.matching.match`: each
  true bubble's best reconstructed bubble (the one covering most of its
  voxels), their IoU, and whether it is found (IoU >= 0.5), missed or merged
  with another; reconstructed bubbles that are no true bubble's best are
  spurious;
* each match's size error: area (2D, mm^2) or volume (3D, mm^3) of both
  bubbles' voxels, and their equivalent diameters (mm), reconstructed minus
  true; the distance of their centroids (mm, of the whole meshes).

With ``write``, ``evaluation.json`` (the same dictionary) and
``evaluation.png`` (truth against reconstruction; a 4D folder adds its DDI per
subscan) go into the reconstruction folder, each atomically, and are added
to its manifest (:func:`bubsub.clients.pipeline.results.outputs.add_outputs`), so
that a later ``--overwrite`` run into that folder removes them with the rest.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bubsub.clients.pipeline.evaluation.evaluate4d import evaluate_dynamic
from bubsub.clients.pipeline.evaluation.scoring import json_scores, score_folder, simulation_meta
from bubsub.clients.pipeline.results.figures import subplots
from bubsub.clients.pipeline.results.outputs import add_outputs, folder_problem, json_default
from bubsub.core.io.atomic import atomic_path, atomic_write_text

__all__ = ["evaluate_dir", "write_evaluation", "write_picture", "EVALUATION", "PICTURE"]

#: The evaluation's file, in the reconstruction folder.
EVALUATION = "evaluation.json"
#: Its picture: truth against reconstruction.
PICTURE = "evaluation.png"



def evaluate_dir(recon_dir, truth_dir, write=False):
    """Score a reconstruction folder against the simulation folder of its scan (see the module docstring).

    Parameters
    ----------
    recon_dir : str or os.PathLike
        A ``bubsub reconstruct`` folder, a ``subscan_NNNN`` folder of ``bubsub reconstruct4d``, or a
        ``reconstruct4d`` folder (scored per subscan, :func:`bubsub.clients.pipeline.evaluation.evaluate4d.evaluate_dynamic`).
    truth_dir : str or os.PathLike
        The ``bubsub simulate`` folder.
    write : bool
        Also write ``evaluation.json`` and ``evaluation.png`` into ``recon_dir`` (:func:`write_evaluation`).

    Returns
    -------
    dict
        JSON-able. A static folder: ``ddi``, ``scored_on``, ``field_of_view`` (``radius_mm``,
        ``half_height_mm``; None when unknown), ``voxels_scored``, ``voxels``, ``grid_shape``,
        ``grid_extent_mm``, ``bubbles_reconstructed``, ``bubbles_truth``, ``matching`` (counts, median IoU,
        mean and median absolute equivalent-diameter error of the found bubbles), ``matches`` (one entry per
        true bubble), ``spurious_ids``, ``reconstruction`` (its report's delivered objective, iterations,
        stop reason, held-out MSE, seconds) and, for a subscan, ``subscan``. A 4D folder: ``subscans`` (each
        such a dictionary), ``mean_ddi``, ``rows``, ``right_track_fraction``. Both: ``kind`` (``static``,
        ``subscan`` or ``4d``), ``reconstruction_folder``, ``truth_folder`` and, with ``write``, ``files``.

    Raises
    ------
    ValueError
        One line naming what is missing or disagrees (not a simulation folder, no bubbles file, 2D
        against 3D, a 4D folder against a static simulation) and what to run.
    """
    recon_dir, truth_dir = Path(recon_dir), Path(truth_dir)
    meta = simulation_meta(truth_dir)
    ndim = meta["ndim"]
    name = "bubbles.ply" if ndim == 3 else "bubbles.json"
    dynamic_truth = "subscans" in meta
    if (recon_dir / name).is_file():
        kind, images = score_folder(recon_dir, truth_dir, meta)
        out = {"kind": kind, **json_scores(images)}
    elif recon_dir.is_dir() and any(recon_dir.glob(f"subscan_*/{name}")):
        if not dynamic_truth:
            raise ValueError(f"{recon_dir} is a bubsub reconstruct4d folder but {truth_dir} holds a static "
                             f"simulation; score it against the 4D simulation of its scan (bubsub simulate "
                             f"--phantom expanding{ndim}d)")
        out = {"kind": "4d", **evaluate_dynamic(recon_dir, truth_dir, matches=True)}
        images = out.pop("_images")
    else:
        other = "bubbles.json" if ndim == 3 else "bubbles.ply"
        hint = (f" (it holds {other}: a {5 - ndim}D result)" if (recon_dir / other).is_file() else "")
        raise ValueError(f"{recon_dir} holds no {name} nor subscan_NNNN/{name}{hint}; the truth in {truth_dir} is "
                         f"{ndim}D: run bubsub reconstruct (or reconstruct4d) on its {ndim}D scan first")
    out.update(reconstruction_folder=str(recon_dir), truth_folder=str(truth_dir))
    if write:
        out["files"] = [p.name for p in write_evaluation(recon_dir, out, images)]
    return out


def write_evaluation(folder, result, images):
    """Write ``evaluation.json`` and ``evaluation.png`` into ``folder``, atomically, and add them to its manifest.

    Parameters
    ----------
    folder : pathlib.Path
        The reconstruction folder.
    result : dict
        :func:`evaluate_dir`'s (JSON-able).
    images : dict
        The label images of the picture: :func:`bubsub.clients.pipeline.evaluation.scoring.score_bubbles`'s result (a static or subscan folder),
        or for a 4D folder the subscan it shows (``_subscans``: each subscan's DDI).

    Returns
    -------
    list of pathlib.Path
    """

    problem = folder_problem(folder)
    if problem:
        raise ValueError(problem.replace("--out", "the reconstruction folder"))
    files = [folder / EVALUATION, folder / PICTURE]
    atomic_write_text(files[0], json.dumps(_rounded(result), indent=2, default=json_default) + "\n")
    write_picture(files[1], result, images)
    add_outputs(folder, files, command="evaluate")
    return files


def _rounded(value, digits=6):
    """``value`` (nested dicts and lists) with every float to ``digits`` significant digits: what the
    rasterised scores resolve, readable in ``evaluation.json``."""
    if isinstance(value, dict):
        return {k: _rounded(v, digits) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_rounded(v, digits) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(f"{float(value):.{digits}g}")
    return value


def _rgb(t_lab, r_lab):
    """Truth against reconstruction as colours: both gas (grey), truth only (red: missed gas), reconstruction
    only (blue: false gas), neither (white)."""
    t, r = t_lab > 0, r_lab > 0
    img = np.ones(t.shape + (3,))
    img[t & r] = (0.55, 0.55, 0.55)
    img[t & ~r] = (0.85, 0.1, 0.1)
    img[~t & r] = (0.1, 0.3, 0.9)
    return img


def _views(t_lab, r_lab, extent):
    """``[(title, rgb image, imshow extent, origin, axis names)]``: the whole 2D grid, or the three middle
    slices of a 3D one (row 0 at y max, as :mod:`bubsub.core.projection.masks`)."""
    if t_lab.ndim == 2:
        return [("", _rgb(t_lab, r_lab), extent, "upper", "xy")]
    nz, ny, nx = t_lab.shape
    x0, x1, y0, y1, z0, z1 = extent
    kz, ky, kx = nz // 2, ny // 2, nx // 2
    z = z0 + (kz + 0.5) * (z1 - z0) / nz
    y = y1 - (ky + 0.5) * (y1 - y0) / ny
    x = x0 + (kx + 0.5) * (x1 - x0) / nx
    return [(f"xy slice, z = {z:.2f} mm", _rgb(t_lab[kz], r_lab[kz]), (x0, x1, y0, y1), "upper", "xy"),
            (f"xz slice, y = {y:.2f} mm", _rgb(t_lab[:, ky], r_lab[:, ky]), (x0, x1, z0, z1), "lower", "xz"),
            (f"yz slice, x = {x:.2f} mm", _rgb(t_lab[:, ::-1, kx], r_lab[:, ::-1, kx]), (y0, y1, z0, z1), "lower",
             "yz")]


def write_picture(path, result, images):
    """``evaluation.png``: truth against reconstruction on the evaluation grid (3D: three middle slices),
    titled with the DDI and the matching; a 4D folder's adds its DDI per subscan."""
    from matplotlib.patches import Patch



    views = _views(images["_truth_labels"], images["_rec_labels"], images["_extent"])
    per = images.get("_subscans")
    n = len(views) + (per is not None)
    fig, axes = subplots(1, n, figsize=(5.2 * n + 0.6, 5.4), dpi=100, squeeze=False)
    axes = list(axes[0])
    if per is not None:
        ax = axes.pop(0)
        ax.plot([p["subscan"] for p in per], [p["ddi"] for p in per], "o-", color="tab:blue")
        ax.set_xlabel("subscan")
        ax.set_ylabel("DDI (lower is better)")
        ax.set_ylim(bottom=0)
        ax.xaxis.get_major_locator().set_params(integer=True)
        ax.set_title(f"DDI per subscan (mean {result['mean_ddi']:.4f})", fontsize=10)
    for ax, (title, rgb, ext, origin, names) in zip(axes, views):
        ax.imshow(rgb, extent=ext, origin=origin, interpolation="nearest")
        ax.set_xlabel(f"{names[0]} (mm)")
        ax.set_ylabel(f"{names[1]} (mm)")
        if title:
            ax.set_title(title, fontsize=10)
    fig.legend(handles=[Patch(color=(0.55, 0.55, 0.55), label="gas in both"),
                        Patch(color=(0.85, 0.1, 0.1), label="true gas the reconstruction misses"),
                        Patch(color=(0.1, 0.3, 0.9), label="reconstructed gas that is not true gas"),
                        Patch(facecolor="white", edgecolor="black", label="liquid in both")],
               loc="lower center", ncol=4, fontsize=9, frameon=False)
    fig.subplots_adjust(bottom=0.16, top=0.86)
    s = images
    mt = s["matching"]
    where = ""
    if "subscan" in s:
        where = f"subscan {s['subscan']}{' (the highest DDI)' if per is not None else ''}: "
    fig.suptitle(f"Truth against reconstruction, {where}DDI {s['ddi']:.4f} ({s['scored_on']});\n"
                 f"{s['bubbles_truth']} true bubbles: {mt['found']} found, {mt['missed']} missed, "
                 f"{mt['merged']} merged; {mt['spurious']} spurious reconstructed bubbles", fontsize=10)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
