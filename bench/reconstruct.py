"""``python -m bubsub.bench reconstruct``: time, memory and DDI of ``bubsub reconstruct`` on foam3d, phase by phase.

Simulates the foam3d phantom (60 bubbles, 25 cone projections, ``--det-count``
columns by half as many rows; truth from finer meshes) once into a scratch
folder, then runs ``bubsub reconstruct`` on it in a child process
``--repeats`` times and prints, per run, the wall and CPU seconds of each
phase (``report.json``'s ``seconds_parts`` and ``cpu_seconds_parts``), the
child's whole wall time, CPU time and peak RSS (what ``/usr/bin/time -v``
reports), and the DDI against the truth (``bubsub evaluate``).

Targets: under 30 s on 2 cores for 25 x 256 x 512 with a DDI of about
0.005; under 600 MB peak for 25 x 128 x 256.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bubsub.clients.pipeline.evaluation.evaluate import evaluate_dir

PHASES = ("preview", "initial_bubbles", "radius_estimation", "fit", "topology", "validity", "refine", "edge_slivers")


def cli_command(*args):
    """``bubsub ARGS`` with this interpreter, as an argument list for :mod:`subprocess`."""
    return [sys.executable, "-c", "import sys; from bubsub.clients.cli.main import main; sys.exit(main())",
            *map(str, args)]



def _child_run(cmd):
    """Run ``cmd``; its wall seconds, CPU seconds (user + system) and peak RSS (MiB).

    The resource usage is this child's own (``os.wait4``): RUSAGE_CHILDREN's
    peak RSS would be the largest of every child so far (the simulation's too).
    """
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise subprocess.CalledProcessError(proc.returncode, cmd)
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m bubsub.bench reconstruct", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--det-count", type=int, default=512, help="detector columns (rows: half); default 512")
    ap.add_argument("--repeats", type=int, default=1, help="reconstructions of the same scan (default 1)")
    ap.add_argument("--no-topology", action="store_true", help="pass --no-topology to bubsub reconstruct")
    args = ap.parse_args(argv)
    if args.det_count < 16 or args.repeats < 1:
        ap.error("need --det-count >= 16 and --repeats >= 1")
    with tempfile.TemporaryDirectory(prefix="bubsub-bench-") as tmp:
        sim = Path(tmp) / "sim"
        subprocess.run(cli_command("simulate", "--phantom", "foam3d", "--angles", 25, "--det-count", args.det_count,
                            "--out", sim), check=True, stdout=subprocess.DEVNULL)
        rows = []
        for k in range(args.repeats):
            out = Path(tmp) / f"rec{k}"
            extra = ["--no-topology"] if args.no_topology else []
            wall, cpu, rss = _child_run(cli_command("reconstruct", sim / "scan.h5", "--out", out, "--quiet", *extra))

            report = json.loads((out / "report.json").read_text())
            ddi = evaluate_dir(out, sim)["ddi"]
            rows.append((report, wall, cpu, rss, ddi))
    shape = f"25 x {args.det_count // 2} x {args.det_count}"
    print(f"bubsub reconstruct, foam3d (60 bubbles), cone {shape}; seconds wall / CPU (all threads)")
    header = ["run"] + [p.replace("_", " ") for p in PHASES] + ["whole wall s", "whole CPU s", "peak RSS MiB", "DDI",
                                                                 "bubbles"]
    table = []
    for k, (report, wall, cpu, rss, ddi) in enumerate(rows):
        parts, cparts = report.get("seconds_parts", {}), report.get("cpu_seconds_parts", {})
        table.append([str(k)] + [f"{parts.get(p, 0):.1f} / {cparts.get(p, 0):.1f}" for p in PHASES]
                     + [f"{wall:.1f}", f"{cpu:.1f}", f"{rss:.0f}", f"{ddi:.5f}", str(report["bubbles"])])
    widths = [max(len(r[i]) for r in [header] + table) for i in range(len(header))]
    for r in [header, ["-" * w for w in widths]] + table:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)))
    print("whole: the child process (imports, reading, outputs and pictures included); peak RSS as /usr/bin/time -v")
    return 0


if __name__ == "__main__":
    sys.exit(main())
