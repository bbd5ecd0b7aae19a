"""``python -m bubsub.bench NAME [options]``: print benchmark tables (``bubsub bench`` runs the same)."""

import importlib
import sys

#: Benchmark name -> (module in bubsub.bench, what it measures). ``bubsub bench --help`` lists these.
BENCHMARKS = {
    "projector": ("projector", "forward, gradient and objective of the mesh projector per backend, scaling, peak memory"),
    "reconstruct": ("reconstruct", "bubsub reconstruct on foam3d: wall/CPU seconds per phase, peak RSS, DDI"),
    "remote": ("remote", "a fit against a local projector server versus in-process: HTTP overhead per iteration"),
    "prepare": ("prepare", "raw-data preparation: DDI/MSE with and without each step, peak memory of a prepare"),
    "fov": ("fov", "bubbles cut by the field of view: DDI inside it with and without modelling its boundary"),
    "cluster": ("cluster", "4D and experiment runs in-process versus on a Dask LocalCluster"),
    "attacks": ("attacks", "bounded attacks on a projector server: status codes, memory rise, health latency"),
    "admission": ("admission", "the server's compute memory estimate against its measured peak, per job shape"),
    "deadline": ("deadline", "how soon a projector server answers 504 past its compute timeout, on a heavy job"),
    "scale": ("scale", "bubsub reconstruct on foam columns of ~150/600/2400 bubbles: phases, peak RSS, DDI, growth"),
    "analysis": ("analysis", "bubsub analyse against FoamQuant's voxel route on a simulated column, and its cost"),
    "levels": ("levels", "the fit's data levels against a long full-detector fit from the same start: objective, cost"),
    "detection": ("detection", "small bubbles and edge caps seeded and found, per size class, against the voxel route"),
    "dynamic": ("dynamic", "reconstruct4d on a flowing, coarsening foam per subscan: found, merged, anew, small, "
                           "track purity, cost, beside the voxel route"),
    "bubbles": ("bubbles", "BubSub on one experiment case, bubble by bubble: missed, merged, spurious, boundary error"),
    "parameters": ("parameters", "bubsub reconstruct with one parameter changed at a time: DDI, iterations, seconds "
                                 "(the tables of docs/parameters.md)"),
}


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    name = argv.pop(0) if argv and not argv[0].startswith("-") else "projector"
    if name not in BENCHMARKS:
        print(f"unknown benchmark {name!r}; choose one of {', '.join(BENCHMARKS)}", file=sys.stderr)
        return 2
    module = importlib.import_module(f"bubsub.bench.{BENCHMARKS[name][0]}")
    return module.main(argv)


if __name__ == "__main__":
    sys.exit(main())
