"""``bubsub reconstruct``: BubSub on one static scan file."""

from __future__ import annotations

import sys

from bubsub.clients.cli.args import positive_float, positive_int

def cmd_reconstruct(args):
    from bubsub.core.io.scanfile import read_scan

    from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, load_initial, reconstruct, write_outputs

    scan = read_scan(args.scan)
    settings = ReconstructionSettings(
        iterations=args.iterations, control_points=args.control_points, levels=args.levels,
        radius=args.radius, estimate_radii=not args.no_radius_estimation, supersampling=args.supersampling,
        holdout=args.holdout, progress=not args.quiet,
    )
    init = load_initial(args.init, scan.bubble_contrast, args.levels) if args.init else None
    factory = None
    client = None
    jobs = []
    if args.server:
        from bubsub.clients.remote.client import ProjectorClient

        client = ProjectorClient(args.server, token=args.token)

        def factory(geometry, data, surfaces):
            job = client.create_job(geometry, data=data, surfaces=surfaces, supersampling=args.supersampling)
            jobs.append(job)
            return job

    try:
        rec = reconstruct(scan, settings, init=init, projector_factory=factory)
    finally:
        if client is not None:
            for job in jobs:  # free the server's memory now rather than at expiry
                try:
                    job.delete()
                except Exception as exc:  # noqa: BLE001 - the result matters more than the clean-up
                    print(f"bubsub reconstruct: could not delete remote job: {exc}", file=sys.stderr)
            client.close()
    files = write_outputs(args.out, rec, scan_path=args.scan)
    r = rec.report
    state = " (interrupted: partial result)" if r["interrupted"] else ""
    print(f"{r['bubbles']} bubbles, {r['iterations']} iterations, objective {r['initial_objective']:.4g} -> "
          f"{r['final_objective']:.4g}, {r['seconds_total']:.1f} s{state}")
    if "holdout_mse" in r:
        print(f"held-out projection MSE ({r['holdout_projections']} projections): {r['holdout_mse']:.4g}")
    print("wrote " + ", ".join(str(p) for p in files.values()))
    return 130 if r["interrupted"] else 0


def register(sub):
    """Add the command's parser to ``sub`` (argparse subparsers)."""
    p = sub.add_parser("reconstruct", help="reconstruct bubbles from a scan file")
    p.add_argument("scan", help="HDF5 scan file (Data Exchange layout)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--iterations", type=int, default=80, help="BFGS iterations (default 80)")
    p.add_argument("--control-points", type=positive_int, help="control points per bubble (3D: 12, 42, 162; default 42; 2D default 9)")
    p.add_argument("--levels", type=int, default=2, help="subdivision levels (default 2)")
    p.add_argument("--radius", type=positive_float, help="constant initial radius in mm (default: from the voxel preview)")
    p.add_argument("--no-radius-estimation", action="store_true", help="skip the radius-only pre-fit")
    p.add_argument("--init", help="initial control mesh: a previous reconstruction's control.ply / control.json")
    p.add_argument("--holdout", choices=("odd", "even"), help="keep these projections aside and report their MSE")
    p.add_argument("--supersampling", type=positive_int, default=1, help="rays per pixel and axis (default 1)")
    p.add_argument("--server", help="URL of a bubsub projector server to fit against (default: local)")
    p.add_argument("--token", help="bearer token for --server")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_reconstruct)
