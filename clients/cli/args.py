"""Argument types shared by the ``bubsub`` commands.

Each refuses a bad value while the command line is parsed, before any data
is read or computed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bubsub.clients.cluster.engine import spec_from_options
from bubsub.clients.pipeline.outputs import folder_problem

__all__ = ["positive_int", "non_negative_int", "int_at_least", "positive_float", "non_negative_float",
           "existing_file", "output_folder", "add_output_arguments", "add_cluster_arguments", "spec_from_args"]


def _number(text, kind):
    try:
        return kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be {'an integer' if kind is int else 'a number'}, got {text!r}") from None


def positive_int(text):
    v = _number(text, int)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return v


def non_negative_int(text):
    v = _number(text, int)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or a positive integer, got {text}")
    return v


def int_at_least(least, why):
    """An argument type: an integer of at least ``least``; ``why`` says why in the refusal."""

    def parse(text):
        v = _number(text, int)
        if v < least:
            raise argparse.ArgumentTypeError(f"must be at least {least} ({why}), got {text}")
        return v

    parse.__name__ = f"int_at_least_{least}"
    return parse


def positive_float(text):
    v = _number(text, float)
    if not (v > 0 and v != float("inf")):
        raise argparse.ArgumentTypeError(f"must be positive and finite, got {text}")
    return v


def non_negative_float(text):
    v = _number(text, float)
    if not (v >= 0 and v != float("inf")):
        raise argparse.ArgumentTypeError(f"must be 0 or a positive finite number, got {text}")
    return v


def existing_file(text):
    p = Path(text)
    if not p.exists():
        where = "" if p.is_absolute() else f" (looked in {Path.cwd()})"
        raise argparse.ArgumentTypeError(f"{text!r} does not exist{where}; give the path of an existing file")
    if p.is_dir():
        inside = sorted(q.name for q in p.glob("*.h5"))[:3]
        hint = f", e.g. {p / inside[0]}" if inside else ""
        raise argparse.ArgumentTypeError(f"{text!r} is a folder, not a file; give a file in it{hint}")
    return text


def output_folder(text):
    """A folder to write into: refused when it names a file or lies under one (the policy on earlier
    results is :func:`bubsub.clients.pipeline.outputs.check_output_folder`)."""
    problem = folder_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(problem)
    return text


def add_output_arguments(parser, what="results", default=None):
    """``--out`` (required unless ``default``) and ``--overwrite``, following
    :mod:`bubsub.clients.pipeline.outputs`."""
    note = f"; default {default}" if default else ""
    parser.add_argument("--out", required=default is None, default=default, type=output_folder, metavar="FOLDER",
                        help=f"folder for the {what} (created if missing; a folder holding earlier bubsub "
                             f"results is refused unless --overwrite{note})")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the results of an earlier run in --out (its other files are removed)")


def add_cluster_arguments(parser):
    """Add ``--workers N``, ``--scheduler ADDRESS``, ``--scheduler-file F`` and ``--dashboard`` to ``parser``
    (:func:`spec_from_args` turns them into a :class:`~bubsub.clients.cluster.engine.ClusterSpec`)."""
    g = parser.add_argument_group("cluster (default: in this process; needs the 'cluster' extra otherwise)")
    g.add_argument("--workers", type=positive_int, metavar="N",
                   help="run on an embedded Dask LocalCluster of N worker processes on 127.0.0.1")
    g.add_argument("--scheduler", metavar="ADDRESS",
                   help="run on an existing Dask cluster, tcp://HOST:PORT (also: $DASK_SCHEDULER_ADDRESS)")
    g.add_argument("--scheduler-file", metavar="FILE", help="run on the Dask cluster whose scheduler wrote FILE")
    g.add_argument("--dashboard", action="store_true", help="serve the embedded cluster's dashboard on 127.0.0.1")
    return g


def spec_from_args(args):
    """:func:`~bubsub.clients.cluster.engine.spec_from_options` of parsed :func:`add_cluster_arguments` options."""
    return spec_from_options(args.workers, args.scheduler, args.scheduler_file, args.dashboard)
