"""``bubsub experiment`` and ``bubsub demo``: the paper's figures and the small end-to-end demo."""

from __future__ import annotations

import argparse

from bubsub.clients.cli.args import add_cluster_arguments, add_output_arguments, positive_int, spec_from_args
from bubsub.clients.experiments.fig6 import FIG6_CONFIGS, run_fig6
from bubsub.clients.experiments.runner import EXPERIMENTS, run_experiment


#: The 4D experiments (clients/experiments/fig6.py) and their dimension; the others are in ``EXPERIMENTS``.
DYNAMIC_EXPERIMENTS = {"fig6": 2, "fig6-3d": 3}


def experiment_names():
    """Every name ``bubsub experiment`` takes: the sweeps of ``EXPERIMENTS``, then the 4D ones."""
    return tuple(EXPERIMENTS) + tuple(DYNAMIC_EXPERIMENTS)


def _dynamic_lines(name, ndim):
    c = FIG6_CONFIGS[(ndim, False)]
    beam = "parallel" if ndim == 2 else "cone"
    return (f"  {name:<7} {ndim}D expanding foam: 4D BubSub against voxel baselines per subscan (docs/dynamic.md)\n"
            f"          {c['bubbles']} bubbles, {c['subscans']} subscans of {c['per_subscan']} {beam}-beam projections\n"
            f"          (odd ones held out); methods: bubsub bb sirt (voxel ones binarised by Otsu's threshold)")


def _experiments_epilog():
    lines = ["experiments (the setting swept, its paper values, the methods compared):"]
    for e in EXPERIMENTS.values():
        values = ", ".join(f"{v:g}" for v in e.values)
        lines.append(f"  {e.name:<7} {e.title}\n          {e.variable}: {values}; methods: {' '.join(e.methods)}")
    lines += [_dynamic_lines(name, ndim) for name, ndim in DYNAMIC_EXPERIMENTS.items()]
    lines.append("\nWrites OUT/NAME.csv (one row per run), OUT/NAME.png and OUT/NAME.json (summary); fig6 and fig6-3d "
                 "write fig6.csv (one row per subscan and method), fig6.json, fig6.png and fig7.png, with the "
                 "simulation in OUT/sim and the reconstruction in OUT/bubsub. OUT may hold other experiments; this "
                 "one's earlier results need --resume (continue) or --overwrite (replace).")
    return "\n".join(lines)


def cmd_experiment(args):
    from bubsub.clients.cluster.engine import open_client

    spec = spec_from_args(args)
    if args.name in DYNAMIC_EXPERIMENTS:
        if not spec.in_process:
            raise ValueError(f"{args.name} runs in this process; --workers/--scheduler apply to the other experiments "
                             f"(and to reconstruct4d)")
        return _fig6(args)
    with open_client(spec) as dask_client:
        summary = run_experiment(args.name, args.out, quick=args.quick, seeds=args.seeds, values=args.values,
                                 methods=args.methods, resume=args.resume, overwrite=args.overwrite,
                                 progress=not args.quiet, client=dask_client)
    return 130 if summary["interrupted"] else 0  # Ctrl-C: the finished runs are written; --resume continues


def _fig6(args):
    if args.values or args.methods or (args.seeds or 1) != 1:
        raise ValueError(f"{args.name} runs one seed of every method; --values, --methods and --seeds do not apply")
    s = run_fig6(args.out, ndim=DYNAMIC_EXPERIMENTS[args.name], quick=args.quick, progress=not args.quiet,
                 resume=args.resume, overwrite=args.overwrite)
    if s["interrupted"]:
        print(f"{args.name}: interrupted after {len(s['subscans'])} finished subscan(s), kept in {args.out}/bubsub; "
              f"rerun with --resume to continue")
        return 130
    ratio = s["ddi_ratio_bubsub_to_sirt_otsu"]
    print("mean DDI: " + ", ".join(f"{m} {v:.4f}" for m, v in s["mean_ddi"].items() if v is not None)
          + (f" (BubSub / SIRT+Otsu = {ratio:.3f})" if ratio is not None else ""))
    ratios = [f"{s[k]:.3f} ({what})" for k, what in (("warm_to_cold_time", "wall"), ("warm_to_cold_cpu_time", "CPU"))
              if s.get(k) is not None]
    print(f"rows on the right track: {s['right_track_fraction']:.3f} of {s['track_rows']}; "
          f"median warm / cold subscan time: {', '.join(ratios) or 'n/a (no warm subscan)'}")
    print(f"wrote {args.out}/fig6.csv, fig6.json, fig6.png, fig7.png")
    return 0


def cmd_demo(args):
    from bubsub.clients.experiments.demo import demo
    from bubsub.clients.pipeline.results.outputs import check_output_folder

    demo(check_output_folder(args.out, overwrite=args.overwrite), progress=not args.quiet)
    return 0


def register(sub):
    """Add the command's parser to ``sub`` (argparse subparsers)."""
    p = sub.add_parser("experiment", help="reproduce a figure of the paper (CSV + PNG)",
                       description="Reproduce a figure of the BubSub paper: DDI of each method against the "
                                   "simulated truth, per setting and seed (lower DDI is better).",
                       epilog=_experiments_epilog(), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("name", choices=experiment_names(), help="the figure to reproduce (listed below)")
    add_output_arguments(p, "NAME.csv, NAME.png and NAME.json (other experiments' results may share it)")
    p.add_argument("--quick", action="store_true",
                   help="a small version (coarser grids, fewer settings, 1 seed) that runs in about a minute")
    p.add_argument("--seeds", type=positive_int, help="runs per point (default: 10, quick: 1)")
    p.add_argument("--values", type=float, nargs="+", metavar="VALUE",
                   help="the settings to sweep instead of the paper's (projections, photon counts or radius factors)")
    p.add_argument("--methods", nargs="+", metavar="METHOD",
                   help="run only these methods (e.g. bubsub tv; the experiment's list is below)")
    p.add_argument("--resume", action="store_true",
                   help="keep the runs already in OUT/NAME.csv and run only the missing ones (fig6: reuse the "
                        "simulation and the finished subscans)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_cluster_arguments(p)
    p.set_defaults(func=cmd_experiment)

    p = sub.add_parser("demo", help="simulate, reconstruct and evaluate a small 2D foam against FBP",
                       description="Simulate a 2D foam (25 projections), reconstruct it with BubSub, and print "
                                   "the Dice dissimilarity (DDI, 0 = perfect, lower is better) of BubSub, FBP "
                                   "and SIRT against the truth. Takes about a minute.")
    add_output_arguments(p, "demo: simulation/, bubsub/, demo.png and ddi.txt", default="demo-output")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_demo)
