"""The ``bubsub`` command line.

``bubsub simulate``, ``prepare``, ``reconstruct``, ``reconstruct4d``, ``evaluate``, ``analyse``, ``experiment``,
``demo``, ``serve`` and ``bench``; ``bubsub COMMAND --help`` explains each.

Errors are one line on stderr (``bubsub COMMAND: error: ...``) and exit
status 2; ``bubsub --debug COMMAND ...`` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import sys

__all__ = ["main", "build_parser"]

#: The command modules, in the order ``bubsub --help`` lists them; each has ``register(sub)``.
COMMANDS = ("simulate", "prepare", "reconstruct", "reconstruct4d", "evaluate", "analyse", "experiment", "bench")

_EPILOG = """\
Typical use:
  bubsub simulate --phantom foam3d --angles 25 --out sim
  bubsub reconstruct sim/scan.h5 --out rec
  bubsub evaluate rec sim

Parameters and when to change them: docs/parameters.md.
"""


def build_parser():
    import importlib

    from bubsub.clients import version

    ap = argparse.ArgumentParser(
        prog="bubsub", description="Direct mesh reconstruction of wet-foam bubbles from sparse-view X-ray CT.",
        epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--version", action="version", version=f"bubsub {version()}")
    ap.add_argument("--debug", action="store_true", help="show the full traceback of an error")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
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
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a refused argument (already printed): its status
        return exc.code
    if args.command != "serve":  # the server sets its own (BUBSUB_BLAS_THREADS)
        _limit_blas()
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print(f"bubsub {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - one line for the user; --debug shows the rest
        if args.debug:
            raise
        known = isinstance(exc, (ValueError, OSError))
        hint = "" if known else " (bubsub --debug ... shows the traceback)"
        text = str(exc) if known else f"{type(exc).__name__}: {exc}"
        print(f"bubsub {args.command}: error: {text}{hint}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
