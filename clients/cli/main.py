"""The ``bubsub`` command line.

``bubsub simulate``, ``prepare``, ``reconstruct``, ``reconstruct4d``, ``evaluate``, ``analyse``, ``experiment``,
``demo``, ``serve`` and ``bench``; ``bubsub COMMAND --help`` explains each.

Errors are one line on stderr (``bubsub COMMAND: error: ...``) and exit
status 2, a refused argument included (the usage is for ``--help``);
``bubsub --debug COMMAND ...`` shows the traceback instead. Warnings are one
line too (``bubsub COMMAND: warning: ...``), without Python's source line.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import warnings

from bubsub.clients import version

__all__ = ["main", "build_parser"]

#: The command modules, in the order ``bubsub --help`` lists them; each has ``register(sub)``.
COMMANDS = ("simulate", "prepare", "reconstruct", "reconstruct4d", "evaluate", "analyse", "experiment", "bench")

_EPILOG = """\
Typical use:
  bubsub simulate --phantom foam3d --angles 25 --out sim
  bubsub reconstruct sim/scan.h5 --out rec
  bubsub evaluate rec sim
  bubsub analyse rec --out analysis

Parameters and when to change them: docs/parameters.md; dynamic scans:
docs/dynamic.md; the foam analysis: docs/analysis.md.
"""


class OneLineParser(argparse.ArgumentParser):
    """argparse's parser whose refusal of an argument is one line naming the problem and where the options are
    listed, instead of the whole usage before it."""

    #: The sub-command being parsed (set by :func:`main`): argparse reports an unknown option from the top parser.
    command = None

    def error(self, message):
        prog = self.prog if self.command is None or self.prog != "bubsub" else f"bubsub {self.command}"
        self.exit(2, f"{prog}: error: {message} ({prog} --help lists the options)\n")


def build_parser():
    ap = OneLineParser(
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


def _one_line_warnings(command):
    """Show warnings as ``bubsub COMMAND: warning: ...`` (Python's shows the file and source line that warned)."""

    def show(message, category, filename, lineno, file=None, line=None):
        print(f"bubsub {command}: warning: {message}", file=sys.stderr if file is None else file)

    warnings.showwarning = show


def main(argv=None):
    parser = build_parser()
    words = sys.argv[1:] if argv is None else list(argv)
    commands = next(a.choices for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    OneLineParser.command = next((w for w in words if not w.startswith("-")), None)
    if OneLineParser.command not in commands:
        OneLineParser.command = None
    try:
        args = parser.parse_args(words)
    except SystemExit as exc:  # --help, --version, or a refused argument (already printed): its status
        return exc.code
    finally:
        OneLineParser.command = None
    with warnings.catch_warnings():  # restores the way warnings are shown when main returns (tests call it)
        if not args.debug:
            _one_line_warnings(args.command)
        return _run(args)


def _run(args):
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
        text = "; ".join(part.strip() for part in text.splitlines() if part.strip())  # a library's may be several
        print(f"bubsub {args.command}: error: {text}{hint}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
