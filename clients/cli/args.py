"""Argument types shared by the ``bubsub`` commands.

Each refuses a bad value while the command line is parsed, before any data
is read or computed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bubsub.clients.cluster.engine import spec_from_options
from bubsub.clients.pipeline.results.outputs import folder_problem

__all__ = ["positive_int", "non_negative_int", "int_at_least", "positive_float", "non_negative_float",
           "existing_file", "output_folder", "add_output_arguments", "add_fit_arguments", "slabs_argument",
           "add_slab_arguments", "add_cluster_arguments", "spec_from_args"]


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
    results is :func:`bubsub.clients.pipeline.results.outputs.check_output_folder`)."""
    problem = folder_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(problem)
    return text


def add_output_arguments(parser, what="results", default=None):
    """``--out`` (required unless ``default``) and ``--overwrite``, following
    :mod:`bubsub.clients.pipeline.results.outputs`."""
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


def add_fit_arguments(parser, what):
    """Add the options ``bubsub reconstruct`` and ``bubsub reconstruct4d`` share about the fit, with the same
    types and checks: ``--iterations``, ``--control-points``, ``--levels``, ``--facet-pixels``, ``--holdout``
    and ``--quiet``.

    Parameters
    ----------
    parser : argparse.ArgumentParser
    what : str
        What is fitted, as the help names it (``"the scan"``, ``"each subscan"``).
    """
    parser.add_argument("--iterations", type=non_negative_int, default=80, metavar="N",
                        help=f"most BFGS iterations of the fit of {what} (default 80, the paper's; a fit stops "
                             f"earlier when converged)")
    parser.add_argument("--control-points", type=positive_int, metavar="N",
                        help="control points per bubble of the fit (3D: 12, 42 or 162, default 42; 2D: >= 3, "
                             "default 9); a kept refinement delivers twice as many in 2D, the next icosphere in 3D "
                             "(42 -> 162)")
    parser.add_argument("--levels", type=non_negative_int, default=2, metavar="N",
                        help="Loop/curve subdivision levels of the fitted surface (0-4, default 2); in 3D the most: "
                             "each bubble takes as few as keep its faces within --facet-pixels")
    parser.add_argument("--facet-pixels", type=float, default=0.2, metavar="PX",
                        help="3D: subdivide each bubble only until its flat faces stand at most PX detector pixels "
                             "from a sphere of its size, at least once and at most --levels times (default 0.2; 0: "
                             "every bubble at --levels; docs/scale.md)")
    parser.add_argument("--holdout", choices=("odd", "even"),
                        help=f"keep these projections of {what} aside and report their MSE (a check against "
                             f"over-fitting)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars or phase lines")


def slabs_argument(text):
    """``--slabs``: a positive integer or ``auto``."""
    if text == "auto":
        return None
    return positive_int(text)


def add_slab_arguments(parser, what, halo_default="a preview of the central rows"):
    """Add the group of ``--slabs N|auto`` and ``--slab-halo ROWS`` to ``parser`` and return it.

    Parameters
    ----------
    parser : argparse.ArgumentParser
    what : str
        What the slabs cut, as the help names it (``"the scan"``, ``"each subscan"``).
    halo_default : str
        Where the default halo's bubble radius comes from.
    """
    g = parser.add_argument_group("slabs (parallel-beam 3D scans; docs/large-scans.md)")
    g.add_argument("--slabs", type=slabs_argument, default="auto", metavar="N|auto",
                   help=f"reconstruct {what} in N slabs of detector rows, each read and fitted on its own "
                        f"(default auto: one slab per about 8 million detector pixels read; 1: {what} whole)")
    g.add_argument("--slab-halo", type=positive_int, metavar="ROWS",
                   help=f"rows read above and below each slab's own rows (default: 1.5 x the largest bubble "
                        f"radius in {halo_default})")
    return g
