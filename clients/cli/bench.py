"""``bubsub bench``: benchmark tables."""

from __future__ import annotations

import argparse

_EPILOG = """\
benchmarks:
  projector   forward and gradient of the mesh projector: ms per call, rays/s,
              per backend (native, embreex) and against trimesh
  remote      a fit against a local projector server versus in-process:
              the HTTP overhead per iteration

Each benchmark has its own options; list them with
  bubsub bench projector --help
  bubsub bench remote --help
"""


def cmd_bench(args):
    from bubsub.bench.__main__ import main as bench_main

    return bench_main([args.name, *args.options])


def register(sub):
    """Add the command's parser to ``sub`` (argparse subparsers)."""
    p = sub.add_parser("bench", help="print a benchmark table (projector or remote)",
                       description="Print a benchmark table.", epilog=_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("name", nargs="?", choices=("projector", "remote"), default="projector",
                   help="which benchmark (default projector)")
    p.add_argument("options", nargs=argparse.REMAINDER,
                   help="options of that benchmark (bubsub bench NAME --help lists them)")
    p.set_defaults(func=cmd_bench)
