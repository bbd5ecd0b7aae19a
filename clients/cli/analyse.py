"""``bubsub analyse``: foam physics from a reconstruction's meshes (tables and pictures)."""

from __future__ import annotations

import argparse
from pathlib import Path

from bubsub.clients.cli.args import add_output_arguments, positive_float, positive_int

_DESCRIPTION = """\
Measure a reconstructed foam: per bubble its size, sphericity, shape tensor, internal strain
and coordination; the contacts (pairs of bubbles closer than --contact-gap) with their gap,
contact point, branch vector and film area; liquid fraction and texture on a Cartesian grid
and in cylindrical shells about the rotation axis. On a reconstruct4d folder also per bubble
and subscan dV/dt, the growth law d(V^(2/3))/dt = k (Z - Z0), T1 events, coalescences and
disappearances, and the size distribution over time.

Writes into --out: bubbles.csv, contacts.csv, regions_grid.csv, regions_shells.csv (each with
its column sidecar), summary.json and sizes.png, sphericity.png, coordination.png,
liquid_fraction.png; 4D adds rates.csv, t1_events.csv, track_events.csv, sizes.csv,
size_distribution.csv, growth_law.png and t1_map.png. Definitions: docs/analysis.md.
"""


def _rec_folder(text):
    p = Path(text)
    if not p.exists():
        raise argparse.ArgumentTypeError(f"{text!r} does not exist")
    if not p.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is a file; give the output folder of bubsub reconstruct or "
                                         f"reconstruct4d")
    return text


def _same_folder(rec, out):
    rec, out = Path(rec).resolve(), Path(out).resolve()
    return out == rec or (out.parent == rec and out.name.startswith("subscan_"))


def cmd_analyse(args):
    from bubsub.clients.analysis.folders import analyse, reconstruction_kind
    from bubsub.clients.pipeline.results.outputs import check_output_folder

    if _same_folder(args.rec, args.out):
        raise ValueError("--out must be a folder of its own, not the reconstruction's folder (its results would be "
                         "replaced)")
    reconstruction_kind(args.rec)  # a folder that is no reconstruction is refused before --out is looked at
    out = check_output_folder(args.out, overwrite=args.overwrite)
    progress = None if args.quiet else print
    result = analyse(args.rec, contact_gap=args.contact_gap, domain=args.domain, radius=args.radius, grid=args.grid,
                     shells=args.shells, progress=progress)
    files = result.write(out, overwrite=True, pictures=not args.no_pictures)
    s = result.summary
    if result.kind == "3d":
        coord, cut = s["mean_coordination"], s["bubbles_truncated"]
        cut = "field of view unknown" if cut is None else f"{cut} cut by the field of view"
        print(f"{s['bubbles']} bubbles ({cut}), {s['contacts']} contacts at a {s['contact_gap_mm']:.4g} mm gap"
              + (f", mean coordination {coord:.2f}" if coord is not None else "")
              + (f", liquid fraction {s['liquid_fraction']:.3f} in the {s['domain']['kind']} of "
                 f"{s['domain']['source']}" if s["liquid_fraction"] is not None else ""))
    else:
        law = s["growth_law"]
        fit = (f"growth law k = {law['slope']:.3g} +- {law['slope_stderr']:.2g}, Z0 = {law['z0']:.3g} +- "
               f"{law['z0_stderr']:.2g}" if law.get("z0") is not None else f"no growth law ({law.get('reason')})")
        fractions = [p["liquid_fraction"] for p in s["per_subscan"] if p.get("liquid_fraction") is not None]
        liquid = (f"; liquid fraction {min(fractions):.3f} to {max(fractions):.3f} in the {s['domain']['kind']} of "
                  f"{s['domain']['source']}" if fractions else "")
        print(f"{s['subscans']} subscans at a {s['contact_gap_mm']:.4g} mm contact gap: {s['t1_events']} T1 events, "
              f"{s['coalescences']} coalescences, {s['disappearances']} disappearances; {fit}{liquid}")
    print(f"wrote {len(files)} files to {args.out}")
    return 0


def register(sub):
    """Add the command's parser to ``sub`` (argparse subparsers)."""
    p = sub.add_parser("analyse", help="foam physics from a reconstruction: shapes, contacts, coordination, liquid "
                                       "fraction; growth law and T1 events in 4D",
                       description=_DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("rec", type=_rec_folder, metavar="REC", help="output folder of bubsub reconstruct (3D) or "
                                                                "reconstruct4d")
    add_output_arguments(p, "tables, summary and pictures")
    p.add_argument("--contact-gap", type=positive_float, metavar="MM",
                   help="bubbles whose surfaces come closer than this are in contact (default: one voxel of the "
                        "reconstruction's voxel preview, the field of view's diameter / 160; docs/analysis.md)")
    p.add_argument("--domain", metavar="SPEC",
                   help="the analysed domain, the sample (air around it would count as liquid): 'sample' (default: "
                        "the simulated sample from the phantom.json beside the scan, else the field of view), "
                        "'fov', 'box:X0,X1,Y0,Y1,Z0,Z1' or 'cylinder:R[,Z0,Z1]' about the rotation axis, mm; "
                        "cut to the field of view; summary.json says which was used")
    p.add_argument("--radius", type=positive_float, metavar="MM",
                   help="shorthand for --domain cylinder:MM (over the field of view's height)")
    p.add_argument("--grid", type=positive_int, nargs=3, metavar=("NX", "NY", "NZ"),
                   help="cells of the Cartesian grid (default: cells about three bubble diameters wide)")
    p.add_argument("--shells", type=positive_int, metavar="N",
                   help="cylindrical shells about the rotation axis (default: about 1.5 bubble diameters wide)")
    p.add_argument("--no-pictures", action="store_true", help="write the tables and summary only (the pictures "
                                                              "take a second each)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=cmd_analyse)
