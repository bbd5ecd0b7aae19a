"""``bubsub prepare``: a raw beamline scan (Data Exchange HDF5 or TIFF folder) to a scan file."""

from __future__ import annotations

import argparse
import re

from bubsub.clients.cli.args import positive_float, positive_int


def _quantity(kind, name):
    def parse(text):
        from bubsub.core.prep.options import parse_quantity  # all of bubsub.core.prep

        try:
            return parse_quantity(text, kind, name=name)
        except ValueError as exc:  # argparse names the option already
            raise argparse.ArgumentTypeError(re.sub(rf"^{re.escape(name)}:? ", "", str(exc))) from None
    return parse


def _contrast(text):
    v = float(text)
    if v == 0 or v != v:
        raise argparse.ArgumentTypeError(f"must be a non-zero number (1/mm), got {text}")
    return v


def _with_sigterm_as_interrupt(func, *args, **kwargs):
    """Run ``func`` with SIGTERM (a batch system's time limit, ``kill``) raising KeyboardInterrupt, so the
    atomic output removes its temporary file as it does on Ctrl-C."""
    import signal

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGTERM, interrupt)
    except ValueError:  # not the main thread: leave the signal alone
        return func(*args, **kwargs)
    try:
        return func(*args, **kwargs)
    finally:
        signal.signal(signal.SIGTERM, previous)


def cmd_prepare(args):
    from bubsub.core.prep.options import prepare_options
    from bubsub.core.prep.pipeline import prepare

    background = args.background
    options = prepare_options(
        flat=args.flat, no_flat=args.no_flat, flats_before=args.flats_before, repair_pixels=not args.no_repair,
        stripes=args.stripes, double_flat=args.double_flat, delta_beta=args.delta_beta, energy=args.energy,
        distance=args.distance,
        pixel_size=args.pixel_size, roi=args.roi, bin=args.bin, projections=args.projections, center=args.center,
        crop_to_axis=not args.no_crop_to_axis, background=background, foam_radius=args.foam_radius,
        liquid_radius=args.liquid_radius,
        contrast=args.contrast, source_origin=args.source_origin, origin_detector=args.origin_detector,
        theta_units=args.theta_units, slab_mb=args.slab_mb,
    )
    if options.background == "reproject" and options.foam_radius is None:
        raise ValueError("--background reproject needs --foam-radius (mm): the region the foam fills")
    from bubsub.clients.progress import phase

    # a bar per pass on a terminal, one line per pass in a log
    report = _with_sigterm_as_interrupt(prepare, args.raw, args.out, options,
                                        progress=False if args.quiet else phase)
    steps = {s["step"]: s for s in report["steps"]}
    shape = steps["bin"]["output_shape"]
    centre = steps["center"]
    axis = centre["axis_column_raw"]
    print(f"wrote {args.out}: {shape[0]} projections of {tuple(shape[1:])} pixels of "
          f"{steps['bin']['pixel_size_mm'][1] * 1e3:.3g} um; axis at raw column "
          f"{'centre' if axis is None else f'{axis:.2f}'} ({centre['method']}); "
          f"bubble contrast {steps['contrast']['bubble_contrast_per_mm']:+.4g} /mm; {report['seconds']:.1f} s; "
          f"report {args.out}.report.json")
    return 0


def register(sub):
    """Add the command's parser to ``sub`` (argparse subparsers)."""
    p = sub.add_parser("prepare", help="raw counts (Data Exchange HDF5 / TIFF folder) to a scan file for reconstruct",
                       description="Flat/dark correction, bad pixels, phase retrieval, -log, stripes, ROI, binning, "
                                   "rotation centre, background and contrast; see docs/prepare.md.")
    p.add_argument("raw", help="Data Exchange HDF5 file (/exchange/data, data_white, data_dark, theta) or a folder "
                               "of proj*/flat*/dark*.tif with angles.txt")
    p.add_argument("--out", required=True, help="scan file to write (HDF5), plus OUT.report.json")
    g = p.add_argument_group("flat field")
    g.add_argument("--flat", choices=("interp", "mean", "best"), default="interp",
                   help="interp: flats before/after interpolated in time (default); mean; best: best-matching flat")
    g.add_argument("--flats-before", type=int, help="flats taken before the scan (default: half of them)")
    g.add_argument("--no-flat", action="store_true", help="proceed without flats (or darks): normalise each "
                                                           "projection by its open-beam level")
    g.add_argument("--no-repair", action="store_true", help="keep dead/hot pixels as they are")
    g.add_argument("--stripes", choices=("none", "sort", "all"), default="none",
                   help="stripe/ring removal with algotom (default none)")
    g.add_argument("--double-flat", choices=("auto", "on", "off"), default="auto",
                   help="divide out the pixel gains the flats do not show, from the mean of the projections, before "
                        "phase retrieval (default auto: on a sample wider than the detector with --delta-beta)")
    g = p.add_argument_group("phase retrieval")
    g.add_argument("--delta-beta", type=positive_float, help="Paganin phase retrieval with this delta/beta")
    g.add_argument("--energy", type=_quantity("energy", "--energy"), help="photon energy (default keV: 16 or 16keV)")
    g.add_argument("--distance", type=_quantity("length", "--distance"),
                   help="sample-detector distance (default mm: 250, 25cm)")
    g.add_argument("--pixel-size", type=_quantity("length", "--pixel-size"),
                   help="detector pixel size (default mm: 0.003, 3um)")
    g = p.add_argument_group("selection and geometry")
    g.add_argument("--roi", help="ROW0:ROW1,COL0:COL1 in raw detector pixels (end exclusive)")
    g.add_argument("--bin", type=positive_int, default=1, help="bin K x K pixels (default 1)")
    g.add_argument("--projections", help="START:STOP:STEP of the raw projections (e.g. one subscan)")
    g.add_argument("--theta-units", choices=("deg", "rad"), help="override the units of the angles")
    g.add_argument("--center", default="auto", help="auto|vo|pair|none or the raw axis column (default auto)")
    g.add_argument("--no-crop-to-axis", action="store_true",
                   help="keep all ROI columns (default: crop them symmetric about the axis)")
    g.add_argument("--source-origin", type=_quantity("length", "--source-origin"), help="cone beam: source-axis mm")
    g.add_argument("--origin-detector", type=_quantity("length", "--origin-detector"),
                   help="cone beam: axis-detector mm")
    g = p.add_argument_group("background and contrast")
    g.add_argument("--background", default="auto",
                   help="auto (= envelope: rotation-invariant container), reproject (FBP, foam disc filled, "
                        "reprojected), none, or an HDF5 file with /exchange/background (default auto)")
    g.add_argument("--foam-radius", type=_quantity("length", "--foam-radius"),
                   help="radius of the foam region about the axis (mm), for reproject and the contrast estimate")
    g.add_argument("--liquid-radius", type=_quantity("length", "--liquid-radius"),
                   help="radius of a liquid cylinder wider than the detector (the container's inner radius, mm), "
                        "for --background auto; default fitted from the data")
    g.add_argument("--contrast", type=_contrast, help="bubble contrast, gas minus liquid attenuation, 1/mm "
                                                       "(default: estimated; the sign is checked)")
    p.add_argument("--slab-mb", type=positive_float, default=256.0, help="memory per slab, MB (default 256)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_prepare)
