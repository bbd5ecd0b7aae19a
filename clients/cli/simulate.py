"""``bubsub simulate``: a simulated scan and its ground truth."""

from __future__ import annotations

from bubsub.clients.cli.args import add_output_arguments, int_at_least, non_negative_int, positive_float, positive_int
from bubsub.clients.pipeline.results.outputs import check_output_folder, finish_outputs
from bubsub.clients.pipeline.evaluation.simulation import (DYNAMIC_PHANTOMS, PHANTOMS, simulate_dynamic_to_dir,
                                                           simulate_flowing_to_dir, simulate_raw_to_dir,
                                                           simulate_to_dir)


def cmd_simulate(args):
    if args.phantom in DYNAMIC_PHANTOMS:
        if args.angles is not None:
            raise ValueError("a dynamic phantom takes --subscans and --projections-per-subscan, not --angles")
    elif args.subscans is not None or args.projections_per_subscan is not None:
        raise ValueError(f"--subscans and --projections-per-subscan need a dynamic phantom ({', '.join(DYNAMIC_PHANTOMS)})")
    flowing = {k: v for k in ("flow", "vanishing", "coalescences") if (v := getattr(args, k)) is not None}
    if flowing and args.phantom != "flowing3d":
        raise ValueError(f"--{'/--'.join(flowing)} need --phantom flowing3d")
    out = check_output_folder(args.out, overwrite=args.overwrite)
    if args.raw:
        return _simulate_raw(args, out)
    if args.phantom in DYNAMIC_PHANTOMS:
        return _simulate_dynamic(args, out)
    if args.phantom == "column":
        return _simulate_column(args, out)
    scan, truth, meta = simulate_to_dir(out, args.phantom, angles=args.angles or 25, photons=args.photons,
                                        seed=args.seed, beam=args.beam, det_count=args.det_count,
                                        n_bubbles=args.bubbles)
    print(f"wrote {scan} ({meta['angles']} projections, I0={meta['photons']:g}, seed {meta['seed']}), "
          f"ground truth {truth} ({meta['bubbles']} bubbles)")
    return 0


def _simulate_raw(args, out):
    kw = {"n_angles": args.angles or 180, "photons": args.photons}
    if args.det_count:  # keep the 9.6 mm detector of the default 800 columns of 12 um
        kw.update(cols=args.det_count, pixel_size=9.6 / args.det_count)
    raw, truth, meta = simulate_raw_to_dir(out, seed=args.seed, n_bubbles=args.bubbles or 8, **kw)
    print(f"wrote {raw} (raw counts: {meta['angles']} projections of {meta['raw']['rows']} x {meta['raw']['cols']} "
          f"pixels, axis at column {meta['axis_column']:.2f}, delta/beta {meta['delta_beta']:.4g}), ground truth "
          f"{truth} ({meta['bubbles']} bubbles)")
    return 0


def _simulate_column(args, out):
    from bubsub.core.foam.column import column_phantom, simulate_column, write_column  # loads scipy.optimize

    if args.beam == "cone":
        raise ValueError("the column phantom is a parallel-beam scan; drop --beam cone")
    cols = args.det_count or 768
    phantom = column_phantom(args.bubbles or 600, seed=args.seed, rows=cols // 3, cols=cols,
                             pixel_size=0.012 * 768 / cols)
    scan = simulate_column(phantom, n_angles=args.angles or 40, photons=args.photons)
    files, meta = write_column(out, phantom, scan)
    finish_outputs(out, files, command="simulate")
    c = meta["column"]
    print(f"wrote {out / 'scan.h5'} ({meta['angles']} parallel projections of {c['rows']} x {c['cols']}, "
          f"I0={meta['photons']:g}, seed {meta['seed']}), ground truth {out / 'truth.ply'} ({meta['bubbles']} "
          f"bubbles, {c['bubbles_cut_top']} cut by the top and {c['bubbles_cut_bottom']} by the bottom row; gas "
          f"fraction {c['gas_fraction_in_fov']:.3f})")
    return 0


def _simulate_dynamic(args, out):
    if args.phantom == "flowing3d":
        return _simulate_flowing(args, out)
    scan, truth, meta = simulate_dynamic_to_dir(
        out, args.phantom, subscans=args.subscans or 8, projections_per_subscan=args.projections_per_subscan or 50,
        photons=args.photons, seed=args.seed, beam=args.beam, det_count=args.det_count, n_bubbles=args.bubbles)
    print(f"wrote {scan} ({meta['subscans']} subscans of {meta['projections_per_subscan']} projections, "
          f"I0={meta['photons']:g}, seed {meta['seed']}), ground truth per subscan in {truth} "
          f"({meta['bubbles']} bubbles)")
    return 0


def _simulate_flowing(args, out):
    if args.beam == "cone":
        raise ValueError("the flowing3d phantom is a parallel-beam scan; drop --beam cone")
    foam = {k: v for k in ("flow", "vanishing", "coalescences") if (v := getattr(args, k)) is not None}
    scan, truth, meta = simulate_flowing_to_dir(
        out, subscans=args.subscans, projections_per_subscan=args.projections_per_subscan, photons=args.photons,
        seed=args.seed, det_count=args.det_count, n_bubbles=args.bubbles, **foam)
    c, f = meta["column"], meta["flowing"]
    print(f"wrote {scan} ({meta['subscans']} subscans of {meta['projections_per_subscan']} parallel projections of "
          f"{c['rows']} x {c['cols']}, continuous rotation, I0={meta['photons']:g}, seed {meta['seed']}), ground "
          f"truth per subscan in {truth} ({min(f['bubbles_per_subscan'])}-{max(f['bubbles_per_subscan'])} bubbles "
          f"in view, {meta['bubbles']} over the run; flow {f['flow_px_per_subscan']:g} px per subscan, "
          f"{f['vanishing']} vanishing, {len(f['coalescences'])} coalescences; events in {meta['events']})")
    return 0


def register(sub):
    """Add the command's parser to ``sub`` (argparse subparsers)."""
    p = sub.add_parser("simulate", help="simulate a foam scan (scan.h5) and its ground truth",
                       description="Simulate a foam scan (scan.h5, with its liquid background) and write its "
                                   "ground truth (truth.json in 2D, truth.ply in 3D, truth/ per subscan for a "
                                   "dynamic scan) and phantom.json.")
    p.add_argument("--phantom", choices=PHANTOMS + ("column",) + DYNAMIC_PHANTOMS, default="foam2d",
                   help="foam2d / foam3d: random static foam; foam3d-benchmark: the fixed 3D benchmark foam; "
                        "column: a synchrotron foam column (parallel beam, 40 x 256 x 768, about --bubbles 600 "
                        "ellipsoids, cut by the top and bottom rows; docs/scale.md); "
                        "expanding2d / expanding3d: an expanding foam for a dynamic scan; flowing3d: a foam column "
                        "flowing up through the field of view while it coarsens and coalesces (parallel beam, "
                        "continuous rotation, 12 subscans of 40 x 128 x 384, about --bubbles 150 in view; "
                        "docs/dynamic.md) (default foam2d)")
    p.add_argument("--angles", type=positive_int, help="number of projections (default 25, column 40; static phantoms)")
    p.add_argument("--subscans", type=positive_int, help="dynamic phantoms: number of subscans (default 8, flowing3d 12)")
    p.add_argument("--projections-per-subscan", type=positive_int,
                   help="dynamic phantoms: projections per subscan, one rotation each (default 50, flowing3d 40 "
                        "over 180 degrees)")
    p.add_argument("--flow", type=float, help="flowing3d: upward plug flow, pixels per subscan (default 4)")
    p.add_argument("--vanishing", type=float,
                   help="flowing3d: fraction of the bubbles, the smallest, that shrink to nothing (default 0.12)")
    p.add_argument("--coalescences", type=non_negative_int,
                   help="flowing3d: pairs of touching neighbours that merge (default 4)")
    p.add_argument("--photons", type=positive_float, default=1e4, help="flat-field photon count I0 (default 1e4)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="seed of the phantom and the noise (default 0)")
    p.add_argument("--beam", choices=("parallel", "cone"), help="default: parallel in 2D, cone in 3D")
    p.add_argument("--det-count", type=int_at_least(16, "a bubble must span a few detector columns"),
                   help="detector columns (2D default 2400, 3D 512, column 768 "
                   "and flowing3d 384 with a third as many rows)")
    p.add_argument("--bubbles", type=positive_int, help="number of bubbles (random phantoms)")
    p.add_argument("--raw", action="store_true",
                   help="a raw beamline scan (raw.h5: counts, flats, darks, phase contrast) of a 2D foam in a "
                        "container, for bubsub prepare (default 180 projections, 800 columns)")
    add_output_arguments(p, "scan and ground truth")
    p.set_defaults(func=cmd_simulate)
