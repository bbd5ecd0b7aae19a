"""``bubsub evaluate``: DDI of a reconstruction against a simulation's ground truth."""

from __future__ import annotations

import argparse

from bubsub.clients.pipeline.evaluate import evaluate_dir

DDI_TEXT = ("DDI (Dice dissimilarity) = 1 - 2 |R n T| / (|R| + |T|) of the reconstructed bubbles R and the true "
            "bubbles T on the truth's grid, counting only its voxels inside the field of view (the region the data "
            "see: the reconstruction's report.json, else a column simulation's phantom.json): 0 is a perfect match, "
            "1 no overlap; lower is better.")

_LABELS = {
    "ddi": "DDI (lower is better)",
    "holdout_mse": "held-out projection MSE",
    "final_objective": "final objective 0.5|Px-d|^2",
    "seconds_total": "reconstruction time (s)",
}


def cmd_evaluate(args):
    res = evaluate_dir(args.recon, args.truth)
    print(DDI_TEXT)
    for k, v in res.items():
        label = _LABELS.get(k, k.replace("_", " "))
        print(f"{label:>30}: {v:.4g}" if isinstance(v, float) else f"{label:>30}: {v}")
    return 0


def register(sub):
    """Add the command's parser to ``sub`` (argparse subparsers)."""
    p = sub.add_parser("evaluate", help="Dice dissimilarity (DDI, lower is better) of a reconstruction against a "
                                        "simulation's ground truth",
                       description="Score a reconstruction against a simulation's ground truth. " + DDI_TEXT,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recon", help="output folder of bubsub reconstruct")
    p.add_argument("truth", help="output folder of bubsub simulate")
    p.set_defaults(func=cmd_evaluate)
