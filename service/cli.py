"""``bubsub serve``: run the projection server with uvicorn.

The bubsub command line calls :func:`add_serve_command` on its sub-command parsers;
``python -m bubsub.service`` runs the same command stand-alone.
"""

from __future__ import annotations

import argparse
import sys

__all__ = ["add_serve_command", "run_serve", "main", "settings_from_args", "bind_socket"]

#: The ``serve`` options and the settings they set; every other setting comes from its BUBSUB_* variable.
_OPTIONS = {"host": "--host", "port": "--port", "workers": "--workers", "max_queue": "--max-queue",
            "log_level": "--log-level"}


def _port(text):
    try:
        port = int(text)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"must be a port number from 0 to 65535 (0: any free port), got {text!r}")
    return port


def _count(least):
    def parse(text):
        try:
            value = int(text)
        except ValueError:
            value = least - 1
        if value < least:
            raise argparse.ArgumentTypeError(f"must be an integer >= {least}, got {text!r}")
        return value
    return parse

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
        description="Run the bubsub projection server: an HTTP API that holds a scan and computes the "
                    "projections of bubbles and their gradients, for fits run elsewhere (bubsub reconstruct "
                    "--server URL). API documentation at http://HOST:PORT/docs; details: docs/service.md.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--host", default=None, help="bind address (default: BUBSUB_HOST or 127.0.0.1)")
    p.add_argument("--port", type=_port, default=None, help="port (default: BUBSUB_PORT or 8000; 0: any free port)")
    p.add_argument("--workers", type=_count(1), default=None,
                   help="projections computed at once (default: BUBSUB_WORKERS or min(4, cores))")
    p.add_argument("--max-queue", type=_count(0), default=None, help="requests that may wait (BUBSUB_MAX_QUEUE)")
    p.add_argument("--log-level", default=None, choices=["critical", "error", "warning", "info", "debug"],
                   help="log level (BUBSUB_LOG_LEVEL)")
    p.set_defaults(func=run_serve)
    return p


def settings_from_args(args):
    """:class:`~bubsub.service.config.Settings` from the environment, overridden by ``args``.

    Raises
    ------
    ValueError
        One line naming each bad setting by the option or BUBSUB_* variable that gave it, the value and
        what it must be (instead of pydantic's report).
    """
    from pydantic import ValidationError

    from bubsub.service.config import Settings

    overrides = {key: getattr(args, key) for key in _OPTIONS if getattr(args, key, None) is not None}
    try:
        return Settings(**overrides)
    except ValidationError as exc:
        problems = []
        for err in exc.errors():
            field = str(err["loc"][0]) if err.get("loc") else "?"
            source = _OPTIONS[field] if field in overrides else f"BUBSUB_{field.upper()}"
            what = err.get("msg", "invalid").replace("Input should be", "must be")
            problems.append(f"{source} {what}, got {err.get('input')!r}")
        raise ValueError("; ".join(problems) + " (bubsub serve --help lists the settings)") from None


def bind_socket(host, port):
    """A socket bound to ``host``, ``port``: a bad address or a taken port is one clear error.

    Parameters
    ----------
    host : str
        Address or name of this machine.
    port : int
        0: any free port.

    Returns
    -------
    socket.socket
        Bound (the caller closes it).

    Raises
    ------
    ValueError
        The host is no address of this machine, the port is taken or needs more rights.
    """
    import errno
    import socket

    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                                            flags=socket.AI_PASSIVE)[0]
    except (socket.gaierror, UnicodeError) as exc:
        raise ValueError(f"--host {host!r} is not an address or name this machine knows ({exc}); give an address "
                         f"of this machine, e.g. 127.0.0.1 (this machine only) or 0.0.0.0 (every network)") from None
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if family == socket.AF_INET6:
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 0)
        sock.bind(address)
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise ValueError(f"port {port} on {host} is in use (another server?); stop it or give --port another "
                             f"number (0: any free port)") from None
        if exc.errno == errno.EACCES:
            raise ValueError(f"port {port} needs administrator rights; give --port 1024 or above") from None
        if exc.errno == errno.EADDRNOTAVAIL:
            raise ValueError(f"--host {host!r} is not an address of this machine; give one of its addresses, e.g. "
                             f"127.0.0.1 or 0.0.0.0") from None
        raise ValueError(f"cannot listen on {host} port {port}: {exc.strerror or exc}") from None
    return sock


def run_serve(args):
    """Run the server until SIGTERM/SIGINT; returns the exit status.

    Parameters
    ----------
    args : argparse.Namespace
        From the ``serve`` parser.
    """
    settings = settings_from_args(args)
    # tried before the app is imported and made: a bad address or a taken port is one line here, at once, not
    # uvicorn's startup log
    bind_socket(settings.host, settings.port).close()
    from bubsub.service.app import create_app
    from bubsub.service.server import Server, uvicorn_config

    config = uvicorn_config(create_app(settings), settings)
    Server(config).run()
    return 0


class _OneLineParser(argparse.ArgumentParser):
    """A refused argument is one line (the usage is for ``--help``), as with ``bubsub serve``."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} ({self.prog} --help lists the options)\n")


def main(argv=None):
    """``python -m bubsub.service [serve] [options]``."""
    parser = _OneLineParser(prog="python -m bubsub.service")
    sub = parser.add_subparsers(dest="command")
    add_serve_command(sub)
    argv = list(argv) if argv is not None else None
    raw = sys.argv[1:] if argv is None else argv
    if not raw or raw[0].startswith("-"):
        raw = ["serve", *raw]
    args = parser.parse_args(raw)
    try:
        return args.func(args)
    except (ValueError, OSError) as exc:  # a bad setting, a taken port: one line, as ``bubsub serve``
        print(f"{parser.prog} serve: error: {exc}", file=sys.stderr)
        return 2
