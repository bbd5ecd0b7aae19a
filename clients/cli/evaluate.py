"""``bubsub evaluate``: a reconstruction scored against a simulation's ground truth, written beside it."""

from __future__ import annotations

import argparse

from bubsub.clients.pipeline.evaluation.evaluate import evaluate_dir

DDI_TEXT = ("DDI (Dice dissimilarity) = 1 - 2 |R n T| / (|R| + |T|) of the reconstructed bubbles R and the true "
            "bubbles T on the truth's grid, counting only its voxels inside the field of view (the region the data "
            "see: the reconstruction's report.json, else a column simulation's phantom.json): 0 is a perfect match, "
            "1 no overlap; lower is better.")

_EPILOG = """\
Writes into RECON: evaluation.json (DDI, field of view, one entry per true bubble:
its best reconstructed bubble's id, IoU, sizes and size errors in mm, mm^2 or mm^3;
spurious bubbles; the reconstruction's delivered objective and held-out MSE) and
evaluation.png (truth against reconstruction; a reconstruct4d folder adds its DDI
per subscan). RECON may be a reconstruct folder, a reconstruct4d folder (scored per
subscan against a 4D simulation) or one of its subscan_NNNN folders.
"""


def summary_lines(res):
    """The readable summary ``bubsub evaluate`` prints of :func:`evaluate_dir`'s result ``res``."""
    if res["kind"] == "4d":
        lines = [_one(p, f"subscan {p['subscan']:>3}: ") for p in res["subscans"]]
        track = res["right_track_fraction"]
        lines.append(f"mean DDI {res['mean_ddi']:.4f} over {len(res['subscans'])} subscans; "
                     f"{'n/a' if track is None else f'{100 * track:.1f} %'} of {res['rows']} (subscan, bubble) rows "
                     f"on the right track")
        return lines
    lines = [_one(res, f"subscan {res['subscan']}: " if res["kind"] == "subscan" else "")]
    fov = res["field_of_view"]
    if fov is None:
        lines.append(f"scored on the whole truth grid ({' x '.join(map(str, res['grid_shape']))} voxels)")
    else:
        size = f"radius {fov['radius_mm']:.3g} mm" + (f", half-height {fov['half_height_mm']:.3g} mm"
                                                     if fov["half_height_mm"] is not None else "")
        lines.append(f"scored inside the field of view ({size}): {res['voxels_scored']} of {res['voxels']} voxels of "
                     f"the {' x '.join(map(str, res['grid_shape']))} truth grid")
    m = res["matching"]
    if m["mean_equivalent_diameter_error_mm"] is not None:
        lines.append(f"equivalent diameter of the found bubbles, reconstructed minus true: mean "
                     f"{m['mean_equivalent_diameter_error_mm']:+.4f} mm, median |error| "
                     f"{m['median_abs_equivalent_diameter_error_mm']:.4f} mm")
    r = res.get("reconstruction") or {}
    parts = []
    if r.get("final_objective") is not None:
        parts.append(f"objective {r['final_objective']:.4g}")
    if "iterations" in r:
        parts.append(f"{r['iterations']} iterations ({r.get('stop_reason', 'done')})")
    if "holdout_mse" in r:
        parts.append(f"held-out projection MSE {r['holdout_mse']:.4g}")
    if "seconds_total" in r:
        parts.append(f"{r['seconds_total']:.1f} s")
    if parts:
        lines.append("reconstruction (report.json): " + ", ".join(parts))
    return lines


def _one(s, prefix):
    """One line: the DDI and the matching of a folder (or of a subscan)."""
    m = s["matching"]
    iou = f", median IoU {m['median_iou']:.3f}" if m.get("median_iou") is not None else ""
    n_rec = s["bubbles"] if "bubbles" in s else s["bubbles_reconstructed"]
    return (f"{prefix}DDI (lower is better): {s['ddi']:.4f}; {s['bubbles_truth']} true bubbles: {m['found']} found"
            f"{iou}, {m['missed']} missed, {m['merged']} merged; {m['spurious']} spurious of {n_rec} reconstructed")


def cmd_evaluate(args):
    res = evaluate_dir(args.recon, args.truth, True)
    print(DDI_TEXT)
    for line in summary_lines(res):
        print(line)
    print(f"wrote {args.recon}: " + ", ".join(res["files"]))
    return 0


def register(sub):
    """Add the command's parser to ``sub`` (argparse subparsers)."""
    p = sub.add_parser("evaluate", help="score a reconstruction against a simulation's ground truth (DDI, "
                                        "per-bubble matches and size errors; evaluation.json and .png)",
                       description="Score a reconstruction against a simulation's ground truth. " + DDI_TEXT,
                       epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recon", help="output folder of bubsub reconstruct or reconstruct4d (or a subscan_NNNN folder)")
    p.add_argument("truth", help="output folder of bubsub simulate")
    p.set_defaults(func=cmd_evaluate)
