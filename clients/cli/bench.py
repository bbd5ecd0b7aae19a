"""``bubsub bench``: benchmark tables."""

from __future__ import annotations

import argparse

from bubsub.bench.__main__ import BENCHMARKS, main as bench_main


def _epilog():
    lines = ["benchmarks:"]
    lines += [f"  {name:<11} {what}" for name, (_, what) in BENCHMARKS.items()]
    lines += ["", "Each benchmark has its own options; list them with", "  bubsub bench NAME --help"]
    return "\n".join(lines)


def cmd_bench(args):
    return bench_main([args.name, *args.options])


def register(sub):
    """Add the command's parser to ``sub`` (argparse subparsers)."""
    p = sub.add_parser("bench", help="print a benchmark table (" + ", ".join(BENCHMARKS) + ")",
                       description="Print a benchmark table.", epilog=_epilog(),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("name", nargs="?", choices=tuple(BENCHMARKS), default="projector",
                   help="which benchmark (default projector)")
    p.add_argument("options", nargs=argparse.REMAINDER,
                   help="options of that benchmark (bubsub bench NAME --help lists them)")
    p.set_defaults(func=cmd_bench)
