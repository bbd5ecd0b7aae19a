"""``bubsub reconstruct``: BubSub on one static scan file."""

from __future__ import annotations

import argparse
import sys

from bubsub.clients.cli.args import (add_cluster_arguments, add_fit_arguments, add_output_arguments,
                                     add_slab_arguments, existing_file, positive_float, positive_int, spec_from_args)
from bubsub.clients.pipeline.results.outputs import check_output_folder, write_outputs
from bubsub.clients.remote.jobs import remote_projectors

_EPILOG = """\
Order of work: the arguments, the output folder, the scan file's metadata and its
bubble signal (sign of bubble_contrast, background) and --server are checked first;
then a low-resolution voxel preview finds the bubbles, a radius-only pre-fit sizes
them, and BFGS fits all control vertices. Outputs: bubbles.ply (3D) or bubbles.json
(2D), control.ply|json, bubbles.csv (+ bubbles.csv-metadata.json describing its
columns), report.json and PNG pictures. What each parameter does: docs/parameters.md.
"""


#: Central detector rows whose bubble signal a reconstruction in slabs checks before it starts.
SIGNAL_CHECK_ROWS = 64


def cmd_reconstruct(args):
    from bubsub.core.io.scanfile import read_geometry, read_scan

    from bubsub.clients.cluster.engine import open_client
    from bubsub.clients.pipeline.inputs.checks import check_bubble_signal
    from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, load_initial, reconstruct
    from bubsub.clients.pipeline.regions.slabs import slab_count

    # --resume continues the slabs of an earlier run in --out, so the folder may hold its results
    out = check_output_folder(args.out, overwrite=args.overwrite or args.resume)
    if args.token and not args.server:
        raise ValueError("--token is only used with --server")
    settings = ReconstructionSettings(
        iterations=args.iterations, control_points=args.control_points, levels=args.levels,
        facet_pixels=args.facet_pixels, radius=args.radius, estimate_radii=not args.no_radius_estimation, supersampling=args.supersampling,
        holdout=args.holdout, progress=not args.quiet, background_subtracted=args.background_subtracted,
        preview=args.preview, detector=args.detector, topology=not args.no_topology, repair=not args.no_repair,
        fov_model=args.fov_model, separation=args.separation, refine=not args.no_refine,
        data_levels=args.data_levels, fit_rtol=None if args.fit_rtol == 0 else args.fit_rtol,
    )
    # the settings' values are checked as they are made, the rest with the scan: by the pipeline
    # (reconstruct, reconstruct_slabs), once per scan
    geometry = read_geometry(args.scan)
    spec = spec_from_args(args)
    if args.slabs != 1 and geometry.ndim == 3 and not geometry.is_cone:
        # slabs read the scan piece by piece and after a preview that sets their halo: its signal is checked
        # on its central rows first, so that impossible data cost seconds and leave no folder
        mid, half = geometry.det_rows // 2, max(1, min(geometry.det_rows, SIGNAL_CHECK_ROWS) // 2)
        check_bubble_signal(read_scan(args.scan, rows=(max(0, mid - half), min(geometry.det_rows, mid + half))),
                            background_subtracted=args.background_subtracted, sides=False)
    slabs, halo = slab_count(args.scan, geometry, settings, args.slabs, args.slab_halo,
                             whole_needed=bool(args.init or args.holdout), workers=spec.workers)
    if slabs > 1 or not spec.in_process:
        if args.init:
            raise ValueError("--init needs the scan reconstructed whole (--slabs 1)")
        from bubsub.clients.pipeline.regions.slabs import reconstruct_slabs

        if args.server:
            from bubsub.clients.remote.client import connect  # the 'client' extra

            connect(args.server, args.token).close()  # checked at start, not after the first slab
        with open_client(spec) as dask_client:
            rec = reconstruct_slabs(args.scan, settings, slabs=slabs, halo=halo, client=dask_client, out=out,
                                    resume=args.resume, server=args.server, token=args.token)
        return _finish(args, out, rec)
    scan = read_scan(args.scan)
    if args.holdout and scan.n_angles < 2:
        raise ValueError("--holdout needs a scan with at least two projections")
    init = load_initial(args.init, scan.bubble_contrast, args.levels) if args.init else None
    if init is not None and init[0].ndim != scan.ndim:
        raise ValueError(f"--init {args.init} holds {init[0].ndim}D bubbles but the scan is {scan.ndim}D")
    # the scan's signal and the settings against its dimension are checked by reconstruct()
    with remote_projectors(args.server, args.token, supersampling=args.supersampling,
                           on_cleanup_error=_cleanup_warning) as factory:
        rec = reconstruct(scan, settings, init=init, projector_factory=factory)
    if args.holdout and not rec.report["interrupted"]:
        # the paper's voxel reference on the same projections: 30 BB iterations, x >= 0
        from bubsub.clients.pipeline.evaluation.voxel_baseline import voxel_baseline

        ref = voxel_baseline(scan, args.holdout)
        rec.report["holdout_mse_voxel_bb"] = ref["holdout_mse"]
    return _finish(args, out, rec)


def _cleanup_warning(exc):
    print(f"bubsub reconstruct: could not delete remote job: {exc}", file=sys.stderr)


def _finish(args, out, rec):
    """Write the outputs and print the summary; the exit status (130 when interrupted)."""
    files = write_outputs(out, rec, scan_path=args.scan, progress=not args.quiet)
    r = rec.report
    if r.get("slabs"):
        st = r["stitch"]
        print(f"{len(r['slabs'])} slabs (halo {r['slab_halo_rows']} rows, {r['slabs_computed']} computed now): "
              f"{st['owned']} bubbles owned, {st['duplicates_dropped']} seam duplicates dropped, "
              f"{st['claimed_from_halo']} taken from a halo, {st['seam_cut']} cut at a seam")
    print(summary_line(r))
    if "holdout_mse" in r:
        print(f"held-out projection MSE ({r['holdout_projections']} projections): {r['holdout_mse']:.4g}"
              + (f" (voxel BB reference: {r['holdout_mse_voxel_bb']:.4g})" if "holdout_mse_voxel_bb" in r else ""))
    _print_changes(r)
    print(f"wrote {out}: " + ", ".join(p.name for p in files.values()))
    return 130 if r["interrupted"] else 0


def summary_line(r):
    """The line ``bubsub reconstruct`` prints about what it delivered, from its ``report.json`` ``r``.

    The objective is the written bubbles' (``final_objective``); with a kept refined fit the iterations
    read ``fit + refined fit`` and the stop reason is the refined fit's, e.g. ``40 bubbles, objective
    18.03 -> 2.283, 80 + 35 iterations (refined fit: converged), 25.1 s``.
    """
    fit = r.get("fit")
    if fit is not None and r.get("delivered_fit") == "refined fit":
        its = f"{fit['iterations']} + {r['iterations'] - fit['iterations']} iterations (refined fit: "
    else:
        its = f"{r['iterations']} iterations ("
    final = r.get("final_objective")
    return (f"{r['bubbles']} bubbles, objective {r['initial_objective']:.4g} -> "
            f"{'?' if final is None else format(final, '.4g')}, {its}{r.get('stop_reason', 'done')}), "
            f"{r['seconds_total']:.1f} s")


def _print_changes(r):
    """One line each for topology changes and validity repairs (details in report.json)."""
    from collections import Counter

    if r.get("topology") and r["topology"]["changes"]:
        kinds = Counter(c["change"] for c in r["topology"]["changes"])
        print("topology: " + ", ".join(f"{n} {k}" for k, n in sorted(kinds.items())))
    v = r.get("validity") or {}
    if v.get("violations_found"):
        acts = Counter(a["action"] for a in v["actions"])
        left = len(v["violations_remaining"])
        print(f"validity: {len(v['violations_found'])} violation(s) found"
              + (": " + ", ".join(f"{n} {k}" for k, n in sorted(acts.items())) if acts else "")
              + (f"; {left} remain (see report.json)" if left else "; none remain"))


def register(sub):
    """Add the command's parser to ``sub`` (argparse subparsers)."""
    p = sub.add_parser("reconstruct", help="reconstruct bubbles from a scan file",
                       description="Reconstruct the bubbles of a scan file as meshes (BubSub).",
                       epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scan", type=existing_file, help="HDF5 scan file (Data Exchange layout, see docs/architecture.md)")
    add_output_arguments(p, "meshes, table, report and pictures")
    add_fit_arguments(p, "the scan")
    p.add_argument("--data-levels", type=positive_int, metavar="K",
                   help="fit on pixels binned 2^(K-1) x 2^(K-1), ..., 2 x 2, then on the full detector, each level "
                        "warm-started (default: 2 for 3D detectors of at least 96 x 96 pixels, else 1)")
    p.add_argument("--fit-rtol", type=float, default=2e-4, metavar="R",
                   help="a fit level has converged when its objective fell by less than R times itself over 5 "
                        "iterations (default 2e-4; 0: run to --iterations)")
    p.add_argument("--radius", type=positive_float,
                   help="initial radius of every bubble in mm (default: from the voxel preview)")
    p.add_argument("--no-radius-estimation", action="store_true",
                   help="skip the radius-only pre-fit (paper eq. 4-5) before the full fit")
    p.add_argument("--preview", choices=("box", "sirt"), default="box",
                   help="voxel preview for the initial bubbles: box-constrained (default) or SIRT (x >= 0 only)")
    p.add_argument("--detector", choices=("auto", "log", "dt"),
                   help="initial bubble centres in the preview: Laplacian-of-Gaussian blobs, distance-transform "
                        "maxima of its Otsu mask, or auto (both, the one that fits the data best; default in 2D; "
                        "dt is the default in 3D)")
    p.add_argument("--no-topology", action="store_true",
                   help="keep the number of bubbles: no adding, removing, merging or splitting after the fit")
    p.add_argument("--separation", type=float, default=0.0, metavar="STRENGTH",
                   help="penalty keeping bubbles a liquid film apart during the fits, e.g. 1 (docs/robustness.md; "
                        "default 0: off, the repair step separates them after the fit)")
    p.add_argument("--no-refine", action="store_true",
                   help="skip the coarse-to-fine step (control meshes refined once and refitted after the repair, "
                        "kept when the Akaike score improves; docs/robustness.md)")
    p.add_argument("--no-repair", action="store_true",
                   help="only report self-intersecting or overlapping bubbles (report.json), do not repair them")
    fov = p.add_mutually_exclusive_group()
    fov.add_argument("--no-fov-model", dest="fov_model", action="store_false",
                     help="treat the detector's top and bottom rows and the reconstructable cylinder as background "
                          "instead of the edge of what the data see: no preview beyond the field of view, and "
                          "bubbles cut by the edge seeded as smaller spheres inside it (docs/prepare.md)")
    fov.add_argument("--fov-model", dest="fov_model", action="store_true",
                     help="the default: voxel preview over 1.25 times the reconstructable cylinder and bubbles cut "
                          "by the detector's top or bottom seeded at their visible part (docs/prepare.md)")
    p.set_defaults(fov_model=True)
    p.add_argument("--init", type=existing_file,
                   help="initial control mesh: a previous reconstruction's control.ply / control.json")
    p.add_argument("--supersampling", type=positive_int, default=1, help="rays per pixel and axis (default 1)")
    p.add_argument("--background-subtracted", action="store_true",
                   help="the projections hold only the bubbles' signal: accept a scan without "
                        "/exchange/background whose bubble_contrast is positive")
    p.add_argument("--server", metavar="URL",
                   help="URL of a bubsub projector server to fit against (default: local); checked at start")
    p.add_argument("--token", help="bearer token for --server")
    g = add_slab_arguments(p, "the scan")
    g.add_argument("--resume", action="store_true",
                   help="reuse the finished slabs in --out/slabs of an earlier run with the same scan and settings")
    add_cluster_arguments(p)
    p.set_defaults(func=cmd_reconstruct)

