"""``python -m bubsub.bench parameters``: the measured examples of docs/parameters.md, one parameter at a time.

Simulates one foam (2D: ``foam2d``, 12 bubbles, 400 columns, 30 views, seed
3; 3D: ``foam3d``, 8 bubbles, 160 columns, 20 cone views, seed 0), runs
``bubsub reconstruct`` once per case with one argument changed and scores each
result against the truth (``bubsub evaluate``'s DDI), then prints the
markdown table docs/parameters.md quotes: DDI, bubbles, iterations and stop
reason, evaluations, fit seconds, and the whole reconstruction's wall and CPU
seconds (``report.json``; on a shared machine the CPU seconds are the figure
to compare, the wall seconds grow with the load). The first case of a fresh
installation also pays numba's compilation of the kernels, which is cached
on disk for the next.

``--dim 2`` or ``3`` (default both); ``--out DIR`` keeps the simulations and
reconstructions (default a temporary folder; an existing simulation there
is reused); ``--only ARGS ...`` runs only those cases (as in the table's
first column, e.g. ``"--control-points 42"``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

from bubsub.bench.reconstruct import cli_command
from bubsub.clients import version
from bubsub.clients.pipeline.evaluation.evaluate import evaluate_dir

#: (simulate arguments, the cases: reconstruct arguments) per dimension; every case adds --quiet.
CASES = {
    2: (["--phantom", "foam2d", "--bubbles", "12", "--det-count", "400", "--angles", "30", "--seed", "3"],
        ["", "--iterations 5", "--iterations 10", "--iterations 20", "--iterations 40", "--control-points 5",
         "--control-points 17", "--levels 1", "--levels 3", "--no-radius-estimation", "--radius 0.1",
         "--radius 0.1 --no-radius-estimation", "--radius 0.6", "--radius 0.6 --no-radius-estimation"]),
    3: (["--phantom", "foam3d", "--bubbles", "8", "--det-count", "160", "--angles", "20", "--seed", "0"],
        ["--control-points 12", "--control-points 42", "--control-points 162"]),
}


def _quiet_main(argv):
    # a child process: the benchmarks drive the command line as a user does, and import nothing of it
    res = subprocess.run(cli_command(*argv), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"bubsub {' '.join(argv)} exited with {res.returncode}: {res.stderr.strip()}")


def run(ndim, out, only=None):
    """Rows of the table for ``ndim`` (dicts), reconstructions kept in ``out``."""
    sim_args, cases = CASES[ndim]
    sim = Path(out) / f"sim{ndim}d"
    if not (sim / "scan.h5").is_file():
        _quiet_main(["simulate", *sim_args, "--out", str(sim), "--overwrite"])
    rows = []
    for k, case in enumerate(cases):
        if only and case not in only:
            continue
        rec = Path(out) / f"rec{ndim}d_{k:02d}"
        _quiet_main(["reconstruct", str(sim / "scan.h5"), "--out", str(rec), "--overwrite", "--quiet",
                     *shlex.split(case)])
        report = json.loads((rec / "report.json").read_text())
        rows.append({"arguments": case, "ddi": evaluate_dir(rec, sim)["ddi"], "bubbles": report["bubbles"],
                     "iterations": report["iterations"], "stop_reason": report["stop_reason"],
                     "evaluations": report["evaluations"], "seconds_fit": report["seconds_fit"],
                     "seconds_total": report["seconds_total"],
                     "cpu_seconds_total": sum(report["cpu_seconds_parts"].values())})
    return rows


def table(rows):
    """The rows as a markdown table."""
    lines = ["| arguments | DDI | bubbles | iterations (stop reason) | evaluations | fit seconds | total seconds "
             "(wall / CPU) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        name = f"`{r['arguments']}`" if r["arguments"] else "(defaults)"
        lines.append(f"| {name} | {r['ddi']:.4f} | {r['bubbles']} | {r['iterations']} ({r['stop_reason']}) | "
                     f"{r['evaluations']} | {r['seconds_fit']:.2f} | {r['seconds_total']:.1f} / {r['cpu_seconds_total']:.1f} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m bubsub.bench parameters", description=__doc__.split("\n\n")[0])
    ap.add_argument("--dim", type=int, choices=(2, 3), nargs="+", default=[2, 3])
    ap.add_argument("--out", help="keep the simulations and reconstructions here")
    ap.add_argument("--only", nargs="+", metavar="ARGS", help="only these cases")
    args = ap.parse_args(argv)

    with contextlib.ExitStack() as stack:
        out = args.out or stack.enter_context(tempfile.TemporaryDirectory())
        for ndim in args.dim:
            sim_args = " ".join(CASES[ndim][0])
            print(f"\n{ndim}D (bubsub {version()}; bubsub simulate {sim_args}; "
                  f"bubsub reconstruct ... ARGUMENTS --quiet):\n")
            print(table(run(ndim, out, args.only)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
