"""``bubsub evaluate``: DDI of a reconstruction against a simulation's ground truth."""

from __future__ import annotations

from bubsub.clients.pipeline.evaluate import evaluate_dir

def cmd_evaluate(args):
    res = evaluate_dir(args.recon, args.truth)
    for k, v in res.items():
        print(f"{k:>22}: {v:.4g}" if isinstance(v, float) else f"{k:>22}: {v}")
    return 0


def register(sub):
    """Add the command's parser to ``sub`` (argparse subparsers)."""
    p = sub.add_parser("evaluate", help="Dice dissimilarity of a reconstruction against a simulation's ground truth")
    p.add_argument("recon", help="output folder of bubsub reconstruct")
    p.add_argument("truth", help="output folder of bubsub simulate")
    p.set_defaults(func=cmd_evaluate)
