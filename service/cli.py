"""``bubsub serve``: run the projection server with uvicorn.

The lead's CLI calls :func:`add_serve_command` on its sub-command parsers;
``python -m bubsub.service`` runs the same command stand-alone.
"""

from __future__ import annotations

import argparse

__all__ = ["add_serve_command", "run_serve", "main"]

_EPILOG = """\
Every option has a BUBSUB_* environment variable (BUBSUB_HOST, BUBSUB_PORT,
BUBSUB_WORKERS, ...); options given here win. Jobs live in the server's memory,
so the server is one process: --workers sets how many projections it computes at
once (threads; Embree releases the GIL), not uvicorn worker processes.
"""


def add_serve_command(subparsers):
    """Register ``serve`` on an ``argparse`` sub-parsers object.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        From ``parser.add_subparsers()``.

    Returns
    -------
    argparse.ArgumentParser
        The ``serve`` parser; its default ``func`` is :func:`run_serve`.
    """
    p = subparsers.add_parser(
        "serve",
        help="run the projection server (HTTP API for remote fits)",
        description="Run the bubsub projection server.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--host", default=None, help="bind address (default: BUBSUB_HOST or 127.0.0.1)")
    p.add_argument("--port", type=int, default=None, help="port (default: BUBSUB_PORT or 8000)")
    p.add_argument("--workers", type=int, default=None,
                   help="projections computed at once (default: BUBSUB_WORKERS or min(4, cores))")
    p.add_argument("--max-queue", type=int, default=None, help="requests that may wait (BUBSUB_MAX_QUEUE)")
    p.add_argument("--log-level", default=None, choices=["critical", "error", "warning", "info", "debug"],
                   help="log level (BUBSUB_LOG_LEVEL)")
    p.set_defaults(func=run_serve)
    return p


def settings_from_args(args):
    """:class:`~bubsub.service.config.Settings` from the environment, overridden by ``args``."""
    from .config import Settings

    overrides = {
        key: getattr(args, key)
        for key in ("host", "port", "workers", "max_queue", "log_level")
        if getattr(args, key, None) is not None
    }
    return Settings(**overrides)


def run_serve(args):
    """Run the server until SIGTERM/SIGINT; returns the exit status.

    Parameters
    ----------
    args : argparse.Namespace
        From the ``serve`` parser.
    """
    from .app import create_app
    from .server import Server, uvicorn_config

    settings = settings_from_args(args)
    config = uvicorn_config(create_app(settings), settings)
    Server(config).run()
    return 0


def main(argv=None):
    """``python -m bubsub.service [serve] [options]``."""
    parser = argparse.ArgumentParser(prog="python -m bubsub.service")
    sub = parser.add_subparsers(dest="command")
    add_serve_command(sub)
    argv = list(argv) if argv is not None else None
    import sys

    raw = sys.argv[1:] if argv is None else argv
    if not raw or raw[0].startswith("-"):
        raw = ["serve", *raw]
    args = parser.parse_args(raw)
    return args.func(args)
