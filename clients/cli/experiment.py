"""``bubsub experiment`` and ``bubsub demo``: the paper's figures and the small end-to-end demo."""

from __future__ import annotations

from bubsub.clients.cli.args import positive_int

def cmd_experiment(args):
    from bubsub.clients.experiments.runner import run_experiment

    run_experiment(args.name, args.out, quick=args.quick, seeds=args.seeds, values=args.values, methods=args.methods,
                   resume=args.resume, progress=not args.quiet)
    return 0


def cmd_demo(args):
    from bubsub.clients.experiments.demo import demo

    demo(args.out, progress=not args.quiet)
    return 0


def register(sub):
    """Add the command's parser to ``sub`` (argparse subparsers)."""
    p = sub.add_parser("experiment", help="reproduce a figure of the paper (CSV + PNG)")
    p.add_argument("name", choices=("fig1a", "fig1b", "fig5", "fig3a"))
    p.add_argument("--out", required=True)
    p.add_argument("--quick", action="store_true", help="a small version that runs in about a minute")
    p.add_argument("--seeds", type=positive_int, help="runs per point (default: 10, quick: 1)")
    p.add_argument("--values", type=float, nargs="+", help="the settings to sweep instead of the paper's")
    p.add_argument("--methods", nargs="+", help="run only these methods (e.g. bubsub tv)")
    p.add_argument("--resume", action="store_true",
                   help="keep the runs already in OUT/NAME.csv and run only the missing ones")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_experiment)

    p = sub.add_parser("demo", help="simulate, reconstruct and evaluate a small 2D foam against FBP")
    p.add_argument("--out", default="demo-output")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_demo)
