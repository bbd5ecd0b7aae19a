"""``bubsub demo``: simulate a small 2D foam, reconstruct it with BubSub, score it against FBP and SIRT."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bubsub.clients.experiments.runner import run_case
from bubsub.core.io.atomic import atomic_path, atomic_write_text
from bubsub.core.metrics import dice_dissimilarity
from bubsub.core.projection.masks import bubble_mask
from bubsub.clients.pipeline.results.figures import subplots
from bubsub.clients.pipeline.results.outputs import finish_outputs, write_outputs
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, reconstruct
from bubsub.clients.pipeline.evaluation.simulation import simulate_to_dir
from bubsub.core.foam.phantoms import foam2d
from bubsub.core.io.scanfile import read_scan

__all__ = ["demo"]


def demo(out="demo-output", progress=True):
    """Simulate a small 2D foam, reconstruct it, evaluate against FBP; print the DDI table."""

    out = Path(out)
    sim = out / "simulation"
    scan_path, _, _ = simulate_to_dir(sim, "foam2d", angles=25, photons=1e4, seed=0, det_count=1200, n_bubbles=30)
    scan = read_scan(scan_path)
    rec = reconstruct(scan, ReconstructionSettings(progress=progress))
    write_outputs(out / "bubsub", rec, scan_path=scan_path)

    ph = foam2d(0, n_bubbles=30)
    shape, extent = ph.grid(500)  # every method on one 0.02 mm grid
    ours = dice_dissimilarity(bubble_mask(rec.surfaces, shape, extent), bubble_mask(ph.bubbles, shape, extent))
    rows = [("BubSub", ours, rec.report["seconds_total"])]
    for method in ("fbp", "sirt"):
        ddi, sec = run_case(method, scan, ph, shape, extent)
        rows.append((method.upper(), ddi, sec))
    lines = ["method  |    DDI | seconds", "--------|--------|--------"]
    lines += [f"{m:<7} | {d:6.4f} | {s:7.1f}" for m, d, s in rows]
    table = "\n".join(lines)
    atomic_write_text(out / "ddi.txt", table + "\n")
    _demo_plot(out / "demo.png", ph, rec, shape, extent)

    finish_outputs(out, [out / "ddi.txt", out / "demo.png"], command="demo")
    print(table)
    print(f"wrote {out}/bubsub (meshes, CSV, report, overlay), {out}/demo.png, {out}/ddi.txt")
    return rows


def _demo_plot(path, phantom, rec, shape, extent):
    fig, axes = subplots(1, 2, figsize=(11, 5.5), dpi=100)
    axes[0].imshow(rec.preview, extent=rec.preview_extent, cmap="gray")
    axes[0].set_title("voxel preview: non-negative SIRT of 25 projections")
    truth = bubble_mask(phantom.bubbles, shape, extent)
    axes[1].imshow(truth, extent=extent, cmap="gray")
    for s in rec.surfaces:
        v = s.fine().vertices
        v = np.vstack([v, v[:1]])
        axes[1].plot(v[:, 0], v[:, 1], color="tab:orange", lw=1)
    axes[1].set_title("ground truth (white) and BubSub (orange)")
    for ax in axes:
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
