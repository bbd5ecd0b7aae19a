"""``bubsub reconstruct4d``: BubSub on a dynamic scan, subscan by subscan backwards in time."""

from __future__ import annotations

from pathlib import Path

from bubsub.clients.cli.args import (add_cluster_arguments, add_fit_arguments, add_output_arguments,
                                     add_slab_arguments, non_negative_float, positive_int, spec_from_args)


def cmd_reconstruct4d(args):
    from bubsub.core.io.scanfile import read_scan

    from bubsub.clients.cluster.engine import open_client
    from bubsub.clients.pipeline.dynamic4d.chain import DynamicSettings
    from bubsub.clients.pipeline.reconstruct4d import reconstruct_dynamic
    from bubsub.clients.pipeline.results.outputs import check_output_folder, finish_outputs

    # --resume continues the run in --out, so the folder is expected to hold results
    out = Path(args.out) if args.resume else check_output_folder(args.out, overwrite=args.overwrite)
    scan = read_scan(args.scan)
    settings = DynamicSettings(iterations=args.iterations, control_points=args.control_points, levels=args.levels,
                               facet_pixels=args.facet_pixels, holdout=args.holdout,
                               voxel_baseline=args.voxel_baseline, warm_rtol=args.warm_rtol,
                               slabs=args.slabs, slab_halo=args.slab_halo, detect=not args.no_detect,
                               follow_flow=not args.no_follow_flow,
                               progress=not args.quiet)
    with open_client(spec_from_args(args)) as dask_client:
        report = reconstruct_dynamic(scan, out, settings, projections_per_subscan=args.projections_per_subscan,
                                     subscans=args.subscans, resume=args.resume, overwrite=args.overwrite,
                                     client=dask_client, chunks=args.chunks)
    kept = [f"subscan_{p['subscan']:04d}" for p in report["subscans"]]
    files = [f for d in kept for f in (out / d).iterdir() if f.is_file()]
    files += [out / n for n in ("tracks.csv", "tracks.csv-metadata.json", "lineage.csv", "lineage.csv-metadata.json",
                                "report.json", "growth.png", "mse.png", "run.json") if (out / n).is_file()]
    finish_outputs(out, files, command="reconstruct4d")
    t = report["totals"]
    state = " (interrupted: the finished subscans are complete; rerun with --resume)" if report["interrupted"] else ""
    print(f"{report['subscans_complete']} subscans, {t['tracks']} bubble tracks ({t['tracks_ended']} ended), "
          f"{t['seconds']:.1f} s{state}")
    if t["subscans_diverged"]:
        print(f"warning: {t['subscans_diverged']} subscan fit(s) diverged; kept their successor's bubbles "
              f"(see report.json)")
    print(f"wrote {args.out}/subscan_NNNN/, tracks.csv, lineage.csv, report.json, growth.png, mse.png")
    return 130 if report["interrupted"] else 0


def register(sub):
    """Add the command's parser to ``sub`` (argparse subparsers)."""
    p = sub.add_parser("reconstruct4d", help="reconstruct a dynamic scan subscan by subscan, with bubble tracks",
                       description="Reconstruct a dynamic scan (all projections in acquisition order, K per "
                                   "subscan) with BubSub, subscan by subscan backwards in time: the last subscan "
                                   "as bubsub reconstruct does, each earlier one warm-started from its "
                                   "successor's bubbles, whose ids are kept as track ids. Writes each subscan's "
                                   "bubbles in subscan_NNNN/ (the files of bubsub reconstruct), tracks.csv, "
                                   "report.json, growth.png and mse.png; --resume continues an interrupted run. "
                                   "Details and outputs: docs/dynamic.md.")
    p.add_argument("scan", help="HDF5 scan file: all projections in acquisition order")
    add_output_arguments(p, "subscan folders, tracks.csv, report.json and plots")
    p.add_argument("--projections-per-subscan", type=positive_int, metavar="K",
                   help="projections per subscan (default: the file's root attribute projections_per_subscan)")
    p.add_argument("--subscans", metavar="A:B", help="A:B reconstructs subscans A..B-1 (default all)")
    add_fit_arguments(p, "each subscan")
    p.add_argument("--warm-rtol", type=non_negative_float, default=2e-3, metavar="R",
                   help="a warm-started fit stops once 5 iterations lowered the objective by less than this "
                        "fraction (default 2e-3; 0 runs all --iterations)")
    p.add_argument("--voxel-baseline", action="store_true",
                   help="also run the voxel baseline (30 Barzilai-Borwein iterations, x >= 0) per subscan "
                        "and plot its held-out MSE")
    p.add_argument("--no-detect", action="store_true",
                   help="warm subscans only refit their successor's bubbles: no search for bubbles the successor "
                        "lacks or for coalescences (lineage.csv then holds only the tracks that end), and the cold "
                        "start keeps two bubbles on one edge cap")
    p.add_argument("--no-follow-flow", action="store_true",
                   help="fit each subscan as if its foam stood still during it (default: in the frame of the "
                        "flow its tracks measured, else, before they have steps, of the flow along the axis that a "
                        "parallel beam's row sums show, so that its bubbles stand where they are at its mid-time)")
    p.add_argument("--resume", action="store_true", help="continue from the complete subscan folders in --out")
    p.add_argument("--chunks", type=positive_int, default=1, metavar="K",
                   help="cut the subscan chain into K chunks run in parallel, each cold-started at its last "
                        "subscan, bubble ids linked where neighbouring chunks overlap (default 1: one chain)")
    # a subscan is one task already: its slabs run in that task, one after another
    add_slab_arguments(p, "each subscan", halo_default="a preview of the central rows or, in a warm-started "
                       "subscan, of its starting bubbles")
    add_cluster_arguments(p)
    p.set_defaults(func=cmd_reconstruct4d)
