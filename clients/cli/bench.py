"""``bubsub bench``: benchmark tables."""

from __future__ import annotations

import argparse

def cmd_bench(args):
    from bubsub.bench.__main__ import main as bench_main

    return bench_main(args.rest)


def register(sub):
    """Add the command's parser to ``sub`` (argparse subparsers)."""
    p = sub.add_parser("bench", help="print a benchmark table (projector or remote)")
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=cmd_bench)
