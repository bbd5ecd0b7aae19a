"""``python -m bubsub.bench prepare``: what each preparation step is worth on a simulated raw scan.

One realistic raw scan (:mod:`bubsub.core.foam.raw`: decaying and drifting
flats, dead/hot pixels, stripes, off-centre axis, container, phase contrast,
Poisson noise) is prepared with all steps and then with one step changed at
a time; each prepared scan is reconstructed (BubSub, odd projections held
out) and scored against the truth. Columns: DDI of the bubbles, bubbles
found / true, held-out projection MSE (against that variant's own prepared
data, so a consistency measure, not comparable across preparations),
background error (mean |background - analytic container projection| over
the foam's columns), axis error (raw pixels), estimated contrast (truth -0.1/mm).

``--memory``: peak RSS of preparing raw files several times the slab size
(run in a fresh process per size); the files grow by their number of rows,
so the sinograms (which the centre search, the background and the contrast
estimate hold whole, ``n_angles x cols``) stay the same.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from bubsub.clients.pipeline.evaluation.evaluate import evaluate_dir
from bubsub.clients.pipeline.results.outputs import write_outputs
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, reconstruct
from bubsub.clients.pipeline.evaluation.simulation import simulate_raw_to_dir
from bubsub.core.io.scanfile import read_scan
from bubsub.core.prep import background as prep_background, pipeline, prepare, prepare_options

VARIANTS = {
    "all steps": {},
    "flat: mean": {"flat": "mean"},
    "flat: best": {"flat": "best"},
    "no phase retrieval": {"delta_beta": None},
    "no centre search": {"center": "none"},
    "no stripe removal": {"stripes": "none"},
    "no pixel repair": {"repair_pixels": False},
    "background: envelope": {"background": "envelope"},
    "background: reproject": {"background": "reproject", "foam_radius": 3.9},
    "background: none": {"background": "none", "contrast": -0.1},
}


def _background_error(scan, meta):
    s_raw = meta["raw"]
    g = scan.geometry
    px = float(np.linalg.norm(g.vectors[0, 4:6]))
    axis = g.det_count / 2 - 0.5 - float(np.dot(g.vectors[0, 2:4], g.vectors[0, 4:6])) / px ** 2
    s = (np.arange(g.det_count) - axis) * px
    chord = lambda r: 2 * np.sqrt(np.maximum(r * r - s * s, 0))
    r_in, r_out = s_raw["container_radius"], s_raw["container_radius"] + s_raw["wall"]
    truth = s_raw["liquid_mu"] * chord(r_in) + s_raw["wall_mu"] * (chord(r_out) - chord(r_in))
    inside = np.abs(s) < 0.9 * r_in
    return float(np.mean(np.abs(scan.background[:, inside] - truth[None, inside])))


def run_table(out, *, cols=1200, angles=120, bubbles=8, iterations=40, seed=5, only=None):
    out = Path(out)
    raw, _, meta = simulate_raw_to_dir(out, seed=seed, n_bubbles=bubbles, n_angles=angles, cols=cols,
                                       pixel_size=9.6 / cols, rows=4, axis_offset=13.3, photons=2e4)
    base = dict(roi="2:4,:", bin=2, delta_beta=meta["delta_beta"], stripes="sort")
    rows = []
    print(f"raw scan: {angles} projections, {cols} columns of {9.6 / cols * 1e3:.3g} um, binned 2x; "
          f"{bubbles} bubbles; axis at raw column {meta['axis_column']:.2f}; reconstruct {iterations} iterations, "
          f"odd projections held out", flush=True)
    print("| preparation | DDI | bubbles found/true | held-out MSE | background error | axis error (px) | "
          "contrast (1/mm) | prepare s | reconstruct s |")
    print("|---|---|---|---|---|---|---|---|---|", flush=True)
    for name, change in VARIANTS.items():
        if only and name not in only:
            continue
        kw = {**base, **change}
        kw = {k: v for k, v in kw.items() if v is not None}
        d = out / name.replace(" ", "_").replace(":", "")
        d.mkdir(exist_ok=True)
        t0 = time.time()
        try:
            report = prepare(raw, d / "scan.h5", prepare_options(**kw), progress=False)
        except ValueError as exc:
            print(f"| {name} | prepare refused: {exc} | | | | | | | |", flush=True)
            continue
        t1 = time.time()
        steps = {s["step"]: s for s in report["steps"]}
        axis = steps["center"]["axis_column_raw"]
        axis_err = "n/a" if axis is None else f"{axis - meta['axis_column']:+.2f}"
        scan = read_scan(d / "scan.h5")
        bg_err = "n/a" if scan.background is None else f"{_background_error(scan, meta):.4f}"
        try:
            rec = reconstruct(scan, ReconstructionSettings(iterations=iterations, holdout="odd", progress=False))
            write_outputs(d / "rec", rec, scan_path=d / "scan.h5")
            res = evaluate_dir(d / "rec", out)
            t2 = time.time()
            rows.append((name, res))
            print(f"| {name} | {res['ddi']:.4f} | {res['bubbles_reconstructed']}/{res['bubbles_truth']} | "
                  f"{res.get('holdout_mse', float('nan')):.3g} | {bg_err} | {axis_err} | "
                  f"{scan.bubble_contrast:+.4f} | {t1 - t0:.1f} | {t2 - t1:.1f} |", flush=True)
        except (ValueError, RuntimeError) as exc:
            print(f"| {name} | reconstruct failed: {str(exc)[:80]} | | | {bg_err} | {axis_err} | "
                  f"{scan.bubble_contrast:+.4f} | {t1 - t0:.1f} | |", flush=True)
    return rows


#: ``--background auto-full``: the radial background from an FBP of 512 x 512 pixels of every projection,
#: the reference that ``auto`` (a smaller FBP of fewer projections) is compared with
FULL_RADIAL = {"grid": 512, "max_angles": 10 ** 9}


def _memory_child(raw, out, slab_mb, background="auto"):
    import functools


    if background == "auto-full":
        pipeline.radial_background = functools.partial(pipeline.radial_background, **FULL_RADIAL)
        background = "auto"
    t0, c0 = time.time(), time.process_time()
    prepare(raw, out, prepare_options(slab_mb=slab_mb, center="auto", background=background), progress=False)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # MB (Linux: kB)
    print(json.dumps({"peak_rss_mb": peak, "seconds": time.time() - t0, "cpu_seconds": time.process_time() - c0}))


def run_memory(out, *, sizes=(1, 4), slab_mb=32.0, backgrounds=("auto",)):
    """Peak RSS, wall and CPU seconds of ``prepare`` for raw files ``sizes`` x 47 MB, slabs of ``slab_mb``,
    with each background method in turn on the same file."""
    out = Path(out)
    rng = np.random.default_rng(0)
    print(f"slab size {slab_mb:g} MB")
    print("| raw file (MB) | projections x rows x cols | background | peak RSS (MB) | baseline RSS (MB) | seconds | "
          "CPU seconds |")
    print("|---|---|---|---|---|---|---|", flush=True)
    base = subprocess.run([sys.executable, "-c", "import resource, bubsub.core.prep.pipeline, "
                           "bubsub.core.voxel.astra2d, algotom.prep.calculation; "
                           "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)"],
                          capture_output=True, text=True, check=True)
    baseline = float(base.stdout.strip())
    for k in sizes:
        n, rows, cols = 360, 64 * k, 1024  # more rows: a larger file, the same sinograms
        raw = out / f"raw_{k}.h5"
        x = np.arange(cols) - cols / 2 + 3.3
        with h5py.File(raw, "w") as f:
            ds = f.create_dataset("exchange/data", (n, rows, cols), np.uint16, chunks=(1, rows, cols))
            for a in range(0, n, 16):
                th = np.radians(np.arange(a, min(n, a + 16)) * 180.0 / n)[:, None]
                p = 0.002 * 2 * np.sqrt(np.maximum(400.0 ** 2 - x ** 2, 0))[None] - 0.002 * 2 * np.sqrt(
                    np.maximum(60.0 ** 2 - (x[None] - 150 * np.cos(th)) ** 2, 0))
                ds[a:a + len(th)] = (rng.poisson(8000 * np.exp(-p))[:, None, :] + 100).repeat(rows, 1)
            f["exchange/data_white"] = np.full((8, rows, cols), 8100, np.uint16)
            f["exchange/data_dark"] = np.full((4, rows, cols), 100, np.uint16)
            f["exchange/theta"] = np.arange(n) * 180.0 / n
            f["measurement/instrument/detector/pixel_size_x"] = 10.0
        size = raw.stat().st_size / 1e6
        for background in backgrounds:
            res = subprocess.run([sys.executable, "-m", "bubsub.bench.prepare", "--memory-child", str(raw),
                                  str(out / f"scan_{k}.h5"), str(slab_mb), background], capture_output=True, text=True)
            if res.returncode:
                print(res.stderr, file=sys.stderr)
                continue
            r = json.loads(res.stdout.strip().splitlines()[-1])
            print(f"| {size:.0f} | {n} x {rows} x {cols} | {background} | {r['peak_rss_mb']:.0f} | {baseline:.0f} | "
                  f"{r['seconds']:.1f} | {r['cpu_seconds']:.1f} |", flush=True)
            (out / f"scan_{k}.h5").unlink()
        raw.unlink()


def run_background(out, *, angles=360, cols=1024, seed=5):
    """Error and CPU seconds per row of the ring-profile background: the full reference (``auto-full``) and ``auto``.

    One ``bubsub simulate --raw`` scan prepared with one ROI row and no
    background, so every variant sees the same sinogram.
    """
    out = Path(out)
    raw, _, meta = simulate_raw_to_dir(out, seed=seed, n_bubbles=8, n_angles=angles, cols=cols,
                                       pixel_size=9.6 / cols, rows=4, axis_offset=13.3, photons=2e4)
    prepare(raw, out / "scan.h5", prepare_options(roi="2:3,:", delta_beta=meta["delta_beta"], stripes="sort",
                                                  background="none", contrast=-0.1), progress=False)
    scan = read_scan(out / "scan.h5")
    print(f"| scan | FBP | background error | CPU s per row |\n|---|---|---|---|")
    for name, kw in (("auto-full", FULL_RADIAL), ("auto", {})):
        c0 = time.process_time()
        bg = prep_background.radial_background(scan.data, scan.geometry, **kw)
        cpu = time.process_time() - c0
        scan.background = np.broadcast_to(bg[None], scan.data.shape).copy()
        print(f"| seed {seed}: {angles} angles x {scan.geometry.det_count} cols | {name} | "
              f"{_background_error(scan, meta):.4f} | {cpu:.2f} |", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m bubsub.bench prepare", description=__doc__.splitlines()[0])
    ap.add_argument("--out", help="working folder (default: a temporary one)")
    ap.add_argument("--cols", type=int, default=1200)
    ap.add_argument("--angles", type=int, default=120)
    ap.add_argument("--iterations", type=int, default=40)
    ap.add_argument("--memory", action="store_true", help="measure peak RSS against the raw file size instead")
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 4], help="raw sizes, units of 47 MB (--memory)")
    ap.add_argument("--slab-mb", type=float, default=32.0)
    ap.add_argument("--background", nargs="+", default=["auto"],
                    help="background methods of the memory runs (default auto; auto-full: the radial background's "
                         "full reference, 512 x 512 pixels from every projection)")
    ap.add_argument("--background-rows", action="store_true",
                    help="compare the ring-profile background auto with its full reference auto-full (error, CPU s per row)")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--only", nargs="+", choices=list(VARIANTS), metavar="ROW",
                    help="run only these rows of the table (names as printed, e.g. 'all steps')")
    ap.add_argument("--memory-child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.memory_child:
        raw, out, slab, *bg = args.memory_child
        _memory_child(raw, out, float(slab), *bg)
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out or tmp)
        out.mkdir(parents=True, exist_ok=True)
        if args.background_rows:
            run_background(out, angles=args.angles, cols=args.cols, seed=args.seed)
        elif args.memory:
            run_memory(out, sizes=args.sizes, slab_mb=args.slab_mb, backgrounds=args.background)
        else:
            run_table(out, cols=args.cols, angles=args.angles, iterations=args.iterations, only=args.only)
    return 0


if __name__ == "__main__":
    sys.exit(main())
