"""The ``bubsub`` command line.

``bubsub simulate``, ``reconstruct``, ``reconstruct4d``, ``evaluate``, ``experiment``, ``demo``,
``serve`` and ``bench``; ``bubsub COMMAND --help`` explains each.
"""

from __future__ import annotations

import argparse
import sys

__all__ = ["main", "build_parser"]

#: The command modules, in the order ``bubsub --help`` lists them; each has ``register(sub)``.
COMMANDS = ("simulate", "reconstruct", "reconstruct4d", "evaluate", "experiment", "bench")


def build_parser():
    import importlib

    ap = argparse.ArgumentParser(prog="bubsub", description="Direct mesh reconstruction of wet-foam bubbles from sparse-view X-ray CT.")
    sub = ap.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        importlib.import_module(f"bubsub.clients.cli.{name}").register(sub)
    try:
        from bubsub.service.cli import add_serve_command
    except ImportError:  # the service extra is not installed
        pass
    else:
        add_serve_command(sub)
    return ap


def _limit_blas():
    # The projector and the optimiser parallelise themselves; idle BLAS threads
    # spinning after each small matrix product would only take their cores.
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - a dependency, but not a vital one
        return
    threadpool_limits(1, user_api="blas")


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command != "serve":  # the server sets its own (BUBSUB_BLAS_THREADS)
        _limit_blas()
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError, OSError) as exc:
        print(f"bubsub {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"bubsub {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
