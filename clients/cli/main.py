"""The ``bubsub`` command line.

``bubsub simulate``, ``reconstruct``, ``evaluate``, ``experiment``, ``demo``,
``serve`` and ``bench``; ``bubsub COMMAND --help`` explains each.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

__all__ = ["main", "simulate_to_dir"]


def _positive_int(text):
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return v


def _positive_float(text):
    v = float(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return v


# -- simulate ---------------------------------------------------------------------------
PHANTOMS = ("foam2d", "foam3d", "foam3d-benchmark")


def make_phantom(name, seed, n_bubbles=None):
    from bubsub.core.foam import phantoms

    if name == "foam2d":
        return phantoms.foam2d(seed, **({"n_bubbles": n_bubbles} if n_bubbles else {}))
    if name == "foam3d":
        return phantoms.foam3d(seed, **({"n_bubbles": n_bubbles} if n_bubbles else {}))
    if name == "foam3d-benchmark":
        return phantoms.foam3d_benchmark()
    raise ValueError(f"unknown phantom {name!r}; choose one of {PHANTOMS}")


def make_geometry(ndim, beam, n_angles, det_count=None, rows=None):
    """The scans of the paper: 2D parallel over [0, pi), 3D cone over [0, 2 pi)."""
    from bubsub.core import ScanGeometry
    from bubsub.core.foam.simulate import default_geometry_2d

    if ndim == 2:
        # a 14.4 mm detector sees the whole 10 mm square at every angle
        cols = det_count or 2400
        if beam == "parallel":
            return default_geometry_2d(n_angles, det_count=cols, pixel_size=14.4 / cols)
        angles = np.linspace(0, 2 * np.pi, n_angles, endpoint=False)
        return ScanGeometry.cone(angles, source_origin=300.0, origin_detector=15.0, pixel_size=15.2 / cols, cols=cols)
    cols = det_count or 512
    rows = rows or cols // 2
    pixel = 0.06 * 512 / cols
    if beam == "parallel":
        angles = np.linspace(0, np.pi, n_angles, endpoint=False)
        return ScanGeometry.parallel(angles, pixel_size=pixel, cols=cols, rows=rows)
    angles = np.linspace(0, 2 * np.pi, n_angles, endpoint=False)
    return ScanGeometry.cone(angles, source_origin=300.0, origin_detector=15.0, pixel_size=pixel, cols=cols, rows=rows)


def truth_grid(phantom, resolution=None):
    """The grid ground truth and reconstructions are compared on (shape, extent)."""
    if phantom.ndim == 2:
        return phantom.grid(resolution or 1000)
    size = np.asarray(phantom.size)
    voxel = resolution or 0.1
    shape = tuple(int(round(s / voxel)) for s in size[::-1])  # (z, y, x)
    return phantom.grid(shape)


def simulate_to_dir(out, phantom_name="foam2d", *, angles=25, photons=1e4, seed=0, beam=None,
                    det_count=None, n_bubbles=None, method="voxel"):
    """Simulate a scan and write ``scan.h5``, ``truth.json|ply`` and ``phantom.json`` to ``out``."""
    from bubsub.core.io.atomic import atomic_write_text
    from bubsub.core.io.meshio import write_ply, write_polygons_json
    from bubsub.core.io.scanfile import write_scan
    from bubsub.core.foam.simulate import simulate_2d, simulate_3d

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    phantom = make_phantom(phantom_name, seed, n_bubbles)
    beam = beam or ("parallel" if phantom.ndim == 2 else "cone")
    geometry = make_geometry(phantom.ndim, beam, angles, det_count)
    if phantom.ndim == 2:
        scan = simulate_2d(phantom, geometry, photons=photons, seed=seed, method=method)
        truth = out / "truth.json"
        write_polygons_json(truth, phantom.bubbles)
    else:
        scan = simulate_3d(phantom, geometry, photons=photons, seed=seed)
        truth = out / "truth.ply"
        write_ply(truth, phantom.bubbles)
    write_scan(out / "scan.h5", scan)
    shape, extent = truth_grid(phantom)
    meta = {"phantom": phantom_name, "ndim": phantom.ndim, "seed": seed, "size": list(phantom.size),
            "liquid_attenuation": phantom.liquid_attenuation, "bubble_contrast": phantom.contrast,
            "bubbles": len(phantom.bubbles), "grid_shape": list(shape), "grid_extent": list(extent),
            "angles": angles, "photons": photons, "beam": beam, "truth": truth.name}
    atomic_write_text(out / "phantom.json", json.dumps(meta, indent=2))
    return out / "scan.h5", truth, meta


def cmd_simulate(args):
    scan, truth, meta = simulate_to_dir(args.out, args.phantom, angles=args.angles, photons=args.photons,
                                        seed=args.seed, beam=args.beam, det_count=args.det_count,
                                        n_bubbles=args.bubbles)
    print(f"wrote {scan} ({meta['angles']} projections, I0={meta['photons']:g}, seed {meta['seed']}), "
          f"ground truth {truth} ({meta['bubbles']} bubbles)")
    return 0


# -- reconstruct -----------------------------------------------------------------------------
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


# -- evaluate -----------------------------------------------------------------------------------
def evaluate_dir(recon_dir, truth_dir):
    """DDI of a reconstruction against the simulated ground truth (and held-out MSE if any)."""
    from bubsub.core.io.meshio import read_ply, read_polygons_json
    from bubsub.core.metrics import shapes_dice_dissimilarity

    recon_dir, truth_dir = Path(recon_dir), Path(truth_dir)
    meta_path = truth_dir / "phantom.json"
    if not meta_path.is_file():
        raise ValueError(f"{truth_dir} is not a simulation folder (no phantom.json); make one with bubsub simulate")
    meta = json.loads(meta_path.read_text())
    ndim = meta["ndim"]
    name = "bubbles.ply" if ndim == 3 else "bubbles.json"
    if not (recon_dir / name).is_file():
        raise ValueError(f"{recon_dir} holds no {name}; run bubsub reconstruct first")
    reader = read_ply if ndim == 3 else read_polygons_json
    rec = reader(recon_dir / name)
    truth = reader(truth_dir / meta["truth"])
    shape, extent = tuple(meta["grid_shape"]), tuple(meta["grid_extent"])
    out = {"ddi": shapes_dice_dissimilarity(rec, truth, shape, extent), "grid_shape": list(shape),
           "bubbles_reconstructed": len(rec), "bubbles_truth": len(truth)}
    report = recon_dir / "report.json"
    if report.is_file():
        r = json.loads(report.read_text())
        for k in ("holdout_mse", "final_objective", "seconds_total", "iterations"):
            if k in r:
                out[k] = r[k]
    return out


def cmd_evaluate(args):
    res = evaluate_dir(args.recon, args.truth)
    for k, v in res.items():
        print(f"{k:>22}: {v:.4g}" if isinstance(v, float) else f"{k:>22}: {v}")
    return 0


# -- experiment / demo ------------------------------------------------------------------------------
def cmd_experiment(args):
    from bubsub.clients.experiments.runner import run_experiment

    run_experiment(args.name, args.out, quick=args.quick, seeds=args.seeds, values=args.values, methods=args.methods,
                   resume=args.resume, progress=not args.quiet)
    return 0


def cmd_demo(args):
    from bubsub.clients.experiments.runner import demo

    demo(args.out, progress=not args.quiet)
    return 0


def cmd_bench(args):
    from bubsub.bench.__main__ import main as bench_main

    return bench_main(args.rest)


# -- parser -----------------------------------------------------------------------------------------
def build_parser():
    ap = argparse.ArgumentParser(prog="bubsub", description="Direct mesh reconstruction of wet-foam bubbles from sparse-view X-ray CT.")
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="simulate a foam scan (scan.h5) and its ground truth")
    p.add_argument("--phantom", choices=PHANTOMS, default="foam2d")
    p.add_argument("--angles", type=_positive_int, default=25, help="number of projections (default 25)")
    p.add_argument("--photons", type=_positive_float, default=1e4, help="flat-field photon count I0 (default 1e4)")
    p.add_argument("--seed", type=int, default=0, help="seed of the phantom and the noise (default 0)")
    p.add_argument("--beam", choices=("parallel", "cone"), help="default: parallel in 2D, cone in 3D")
    p.add_argument("--det-count", type=_positive_int, help="detector columns (2D default 2400, 3D 512)")
    p.add_argument("--bubbles", type=_positive_int, help="number of bubbles (random phantoms)")
    p.add_argument("--out", required=True, help="output folder")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("reconstruct", help="reconstruct bubbles from a scan file")
    p.add_argument("scan", help="HDF5 scan file (Data Exchange layout)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--iterations", type=int, default=80, help="BFGS iterations (default 80)")
    p.add_argument("--control-points", type=_positive_int, help="control points per bubble (3D: 12, 42, 162; default 42; 2D default 9)")
    p.add_argument("--levels", type=int, default=2, help="subdivision levels (default 2)")
    p.add_argument("--radius", type=_positive_float, help="constant initial radius in mm (default: from the voxel preview)")
    p.add_argument("--no-radius-estimation", action="store_true", help="skip the radius-only pre-fit")
    p.add_argument("--init", help="initial control mesh: a previous reconstruction's control.ply / control.json")
    p.add_argument("--holdout", choices=("odd", "even"), help="keep these projections aside and report their MSE")
    p.add_argument("--supersampling", type=_positive_int, default=1, help="rays per pixel and axis (default 1)")
    p.add_argument("--server", help="URL of a bubsub projector server to fit against (default: local)")
    p.add_argument("--token", help="bearer token for --server")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_reconstruct)

    p = sub.add_parser("evaluate", help="Dice dissimilarity of a reconstruction against a simulation's ground truth")
    p.add_argument("recon", help="output folder of bubsub reconstruct")
    p.add_argument("truth", help="output folder of bubsub simulate")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("experiment", help="reproduce a figure of the paper (CSV + PNG)")
    p.add_argument("name", choices=("fig1a", "fig1b", "fig5", "fig3a"))
    p.add_argument("--out", required=True)
    p.add_argument("--quick", action="store_true", help="a small version that runs in about a minute")
    p.add_argument("--seeds", type=_positive_int, help="runs per point (default: 10, quick: 1)")
    p.add_argument("--values", type=float, nargs="+", help="the settings to sweep instead of the paper's")
    p.add_argument("--methods", nargs="+", help="run only these methods (e.g. bubsub tv)")
    p.add_argument("--resume", action="store_true",
                   help="keep the runs already in OUT/NAME.csv and run only the missing ones")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_experiment)

    p = sub.add_parser("demo", help="simulate, reconstruct and evaluate a small 2D foam against FBP")
    p.add_argument("--out", default="demo-output")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("bench", help="print a benchmark table (projector or remote)")
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=cmd_bench)

    try:
        from bubsub.service.cli import add_serve_command
    except ImportError:  # the service extra is not installed
        pass
    else:
        add_serve_command(sub)
    return ap


def _limit_blas():
    # The projector and the optimiser parallelise themselves; idle BLAS threads
    # spinning after each small matrix product would only take their cores.
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - a dependency, but not a vital one
        return
    threadpool_limits(1, user_api="blas")


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command != "serve":  # the server sets its own (BUBSUB_BLAS_THREADS)
        _limit_blas()
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError, OSError) as exc:
        print(f"bubsub {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"bubsub {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
