"""``bubsub analyse`` on folders: read a reconstruction, analyse it, write the tables and pictures.

:func:`analyse` reads a ``bubsub reconstruct`` folder (``bubbles.ply``,
``bubbles.csv``, ``report.json``) or a ``bubsub reconstruct4d`` folder
(``tracks.csv`` and ``subscan_NNNN/``, each a reconstruct folder) and returns
an :class:`Analysis`: every table as a list of rows with its column
descriptions, and a summary. :meth:`Analysis.write` writes them
(:mod:`bubsub.clients.pipeline.results.outputs` policy) with the pictures of
:mod:`bubsub.clients.analysis.figures`.

Default contact gap
-------------------
One voxel of the reconstruction's voxel preview (``preview.voxel_mm`` of its
report, in 4D the cold start's; in reports that do not give it,
``settings.voxel_size`` or the default preview voxel, the field of view's
diameter over 160): films of wet foams (micrometres) are far thinner than any scan
resolves, so bubbles pressed against each other come out of ``bubsub
reconstruct`` with a small gap (the fit keeps a quarter of a preview voxel
between neighbours); one voxel is four times that, while bubbles apart across
a Plateau border or a liquid node are separated by a sizeable fraction of
their radius. docs/analysis.md gives the numbers.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bubsub.core.analysis.columns import describe, dynamics_columns, named_rows
from bubsub.core.analysis.dynamics import fit_growth_law, growth_rates, size_tables, t1_events, track_events
from bubsub.core.analysis.regions import Domain
from bubsub.core.analysis.snapshot import SNAPSHOT_TABLES, analyse_meshes, default_regions
from bubsub.clients.analysis.domain import analysed_domain
from bubsub.clients.analysis.figures import write_figures
from bubsub.clients.pipeline.results.outputs import check_output_folder, finish_outputs, json_default
from bubsub.core.io.atomic import atomic_write_text
from bubsub.core.io.meshio import read_ply
from bubsub.core.io.tables import csv_metadata_path, write_csv
from bubsub.core.projection.mesh import equivalent_radius

__all__ = ["Analysis", "analyse", "read_reconstruction", "reconstruction_kind", "default_contact_gap",
           "PREVIEW_VOXELS_3D", "TABLE_FILES"]

#: Voxels across the field of view of the default 3D voxel preview (``preview_voxel_size`` of the pipeline).
PREVIEW_VOXELS_3D = 160

#: Table name -> file name.
TABLE_FILES = {"bubbles": "bubbles.csv", "contacts": "contacts.csv", "grid": "regions_grid.csv",
               "shells": "regions_shells.csv", "rates": "rates.csv", "t1": "t1_events.csv",
               "events": "track_events.csv", "sizes": "sizes.csv", "distribution": "size_distribution.csv"}

_TITLES = {"bubbles": "bubbles: size, shape, internal strain, coordination",
           "contacts": "contacts: pairs of bubbles closer than the contact gap",
           "grid": "liquid fraction and texture on a Cartesian grid",
           "shells": "liquid fraction and texture in cylindrical shells about the rotation axis",
           "rates": "growth rates per bubble and subscan", "t1": "T1 neighbour swaps",
           "events": "disappearances, coalescences and appearances", "sizes": "bubble sizes per subscan",
           "distribution": "size distribution per subscan"}


@dataclass
class Reconstruction3D:
    """What ``analyse`` reads of one reconstruct folder."""

    folder: Path
    meshes: list
    ids: list
    report: dict
    truncated: list | None
    volume_in_fov: list | None

    @property
    def field_of_view(self):
        fov = self.report.get("field_of_view_mm")
        return None if fov is None else (float(fov["radius"]), float(fov["half_height"]))


@dataclass
class Analysis:
    """The tables of one analysis.

    Attributes
    ----------
    kind : {"3d", "4d"}
    tables : dict
        Table name -> list of rows (dicts); names in :data:`TABLE_FILES`.
    columns : dict
        Table name -> ``{column: (unit, meaning)}``.
    summary : dict
    """

    kind: str
    tables: dict
    columns: dict
    summary: dict = field(default_factory=dict)

    def write(self, out, *, overwrite=False, pictures=True):
        """Write the tables (CSV with their column sidecars), ``summary.json`` and the pictures into ``out``.

        Returns
        -------
        list of pathlib.Path
            The files written.
        """
        out = check_output_folder(out, overwrite=overwrite)
        out.mkdir(parents=True, exist_ok=True)
        files = []
        for name, rows in self.tables.items():
            path = out / TABLE_FILES[name]
            write_csv(path, rows, list(self.columns[name]), describe=self.columns[name], title=_TITLES[name])
            files += [path, csv_metadata_path(path)]
        if pictures:
            files += write_figures(out, self)
        atomic_write_text(out / "summary.json", json.dumps(self.summary, indent=2, default=json_default) + "\n")
        files.append(out / "summary.json")
        finish_outputs(out, files, command="analyse")
        return files


def _problem(folder):
    p = Path(folder)
    if not p.exists():
        return f"{str(folder)!r} does not exist"
    if not p.is_dir():
        return f"{str(folder)!r} is a file; give the output folder of bubsub reconstruct or reconstruct4d"
    return None


#: What ``bubsub analyse`` says of 2D results: it measures 3D bubbles only.
NOT_2D = "bubsub analyse measures 3D foams (bubbles.ply); 2D reconstructions are not analysed"


def reconstruction_kind(folder):
    """``"3d"`` for a ``bubsub reconstruct`` folder of 3D bubbles, ``"4d"`` for a 3D ``reconstruct4d`` folder.

    Raises
    ------
    ValueError
        One line: a 2D reconstruction (``bubbles.json``, or a ``reconstruct4d`` folder whose subscans
        hold ``bubbles.json``), a 4D folder without its subscan folders, or no reconstruction at all.
    """
    p = Path(folder)
    subscans = [d for d in p.iterdir() if d.is_dir() and d.name.startswith("subscan_")] if p.is_dir() else []
    if (p / "tracks.csv").is_file() and subscans:
        if any((d / "bubbles.ply").is_file() for d in subscans):
            return "4d"
        if any((d / "bubbles.json").is_file() for d in subscans):
            raise ValueError(f"{str(folder)!r} is a 2D reconstruct4d folder (its subscans hold bubbles.json); "
                             f"{NOT_2D}")
        raise ValueError(f"{str(folder)!r}: no complete subscan_NNNN folder with bubbles.ply (an interrupted "
                         f"reconstruct4d run? finish it with bubsub reconstruct4d --resume)")
    if (p / "bubbles.ply").is_file():
        return "3d"
    if (p / "bubbles.json").is_file():
        raise ValueError(f"{str(folder)!r} holds a 2D reconstruction (bubbles.json); {NOT_2D}")
    if (p / "tracks.csv").is_file():
        raise ValueError(f"{str(folder)!r} has tracks.csv but no subscan_NNNN folders (a reconstruct4d folder "
                         f"needs them); bubsub analyse measures their bubbles.ply")
    raise ValueError(f"{str(folder)!r} is not the output of bubsub reconstruct or reconstruct4d (it has neither "
                     f"bubbles.ply nor tracks.csv with subscan_NNNN folders)")


def _read_json(path):
    try:
        doc = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: invalid JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: expected a JSON object")
    return doc


def _fov_columns(table, ids):
    """``truncated`` and ``volume_in_fov_mm3`` of a reconstruct ``bubbles.csv``, in the order of ``ids``."""
    if not table.is_file():
        return None, None
    with open(table, newline="") as fh:
        rows = {int(r["id"]): r for r in csv.DictReader(fh)}
    if not rows or "truncated" not in next(iter(rows.values())):
        return None, None
    missing = [i for i in ids if i not in rows]
    if missing:
        raise ValueError(f"{table}: no row for bubble ids {missing[:5]} of bubbles.ply")
    flags = [int(rows[i]["truncated"]) for i in ids]
    vol = [float(rows[i]["volume_in_fov_mm3"]) if rows[i].get("volume_in_fov_mm3", "") != "" else np.nan
           for i in ids]
    return flags, vol


def read_reconstruction(folder):
    """The fine meshes, ids, report and field-of-view columns of a ``bubsub reconstruct`` folder.

    Raises
    ------
    ValueError
        If the folder is missing, not a 3D reconstruct output, or its files are malformed.
    """
    problem = _problem(folder)
    if problem:
        raise ValueError(problem)
    folder = Path(folder)
    if reconstruction_kind(folder) != "3d":
        raise ValueError(f"{str(folder)!r} is a 4D reconstruction; read its subscan folders")
    meshes, ids = read_ply(folder / "bubbles.ply", with_ids=True)
    if not meshes:
        raise ValueError(f"{folder / 'bubbles.ply'} holds no bubbles")
    report = _read_json(folder / "report.json") if (folder / "report.json").is_file() else {}
    if report.get("dimension", 3) != 3:
        raise ValueError(f"{folder / 'report.json'} describes a {report.get('dimension')}D reconstruction")
    flags, vol = _fov_columns(folder / "bubbles.csv", ids)
    return Reconstruction3D(folder, meshes, ids, report, flags, vol)


def default_contact_gap(report):
    """One preview voxel of the reconstruction (see the module docstring), mm.

    Raises
    ------
    ValueError
        When the report gives neither the preview's voxel size nor the field of view.
    """
    voxel = (report.get("preview") or {}).get("voxel_mm") or (report.get("settings") or {}).get("voxel_size")
    if voxel:
        return float(voxel)
    fov = report.get("field_of_view_mm")
    if not fov or not fov.get("radius"):
        raise ValueError("the reconstruction's report.json gives no field of view to derive the default contact "
                         "gap from; pass --contact-gap MM (contact_gap=)")
    return 2.0 * float(fov["radius"]) / PREVIEW_VOXELS_3D


def _snapshot(rec, gap, options, domain, source):
    return analyse_meshes(rec.meshes, rec.ids, contact_gap=gap, field_of_view=rec.field_of_view,
                          truncated=rec.truncated, volume_in_fov=rec.volume_in_fov, domain=domain,
                          domain_source=source, **options)


def _domain_spec(domain, radius):
    """``domain`` (``--domain``), or ``radius`` as its shorthand ``cylinder:R``."""
    if radius is None:
        return domain
    if domain is not None:
        raise ValueError("give the analysed domain once: --domain or --radius (the shorthand of --domain "
                         "cylinder:R), not both")
    if not (float(radius) > 0 and np.isfinite(float(radius))):
        raise ValueError(f"the domain radius must be positive and finite, got {radius!r} mm")
    return f"cylinder:{float(radius)!r}"


def _fixed_regions(recs, domain, grid, shells):
    """One grid and one set of shells for every subscan of a 4D folder: over ``domain`` (else the bounding
    box of every subscan's bubbles), cells and shells sized from the median equivalent radius of all
    subscans' whole bubbles (:func:`~bubsub.core.analysis.snapshot.default_regions`)."""
    if domain is None:
        domain = Domain.around([m for rec in recs for m in rec.meshes])
    radii = [equivalent_radius(m.volume, 3) for rec in recs
             for k, m in enumerate(rec.meshes) if not (rec.truncated and rec.truncated[k])]
    if not radii:
        radii = [equivalent_radius(m.volume, 3) for rec in recs for m in rec.meshes]
    g0, s0 = default_regions(float(np.median(radii)), domain)
    return domain, (g0 if grid is None else grid), (s0 if shells is None else shells)


def _check_gap(contact_gap):
    if contact_gap is None:
        return None
    gap = float(contact_gap)
    if not (gap > 0 and np.isfinite(gap)):
        raise ValueError(f"the contact gap must be positive and finite, got {contact_gap!r} mm")
    return gap


def analyse(folder, *, contact_gap=None, domain=None, radius=None, grid=None, shells=None, progress=None):
    """Analyse a reconstruct or reconstruct4d output folder.

    Parameters
    ----------
    folder : str or os.PathLike
    contact_gap : float, optional
        mm; default :func:`default_contact_gap` of the (first subscan's) report.
    domain : str or Domain, optional
        The analysed domain (:func:`bubsub.clients.analysis.domain.analysed_domain`): ``"sample"``
        (the default: the simulated sample where known, else the field of view), ``"fov"``,
        ``"box:X0,X1,Y0,Y1,Z0,Z1"``, ``"cylinder:R[,Z0,Z1]"`` or a
        :class:`~bubsub.core.analysis.regions.Domain`; cut to the field of view.
    radius : float, optional
        Shorthand for ``domain="cylinder:R"`` (mm, over the field of view's height).
    grid : (3,) int, optional
    shells : int, optional
        The regions (:func:`bubsub.core.analysis.snapshot.default_regions`); in 4D one grid and one set of
        shells for every subscan.
    progress : callable, optional
        Called with a line of text per analysed subscan.

    Returns
    -------
    Analysis
        Its summary's ``domain`` gives the domain's ``kind``, bounds, ``radius_mm`` and ``source``.
    """
    gap = _check_gap(contact_gap)
    problem = _problem(folder)
    if problem:
        raise ValueError(problem)
    spec = _domain_spec(domain, radius)
    options = {"grid": grid, "shells": shells}
    if reconstruction_kind(folder) == "3d":
        rec = read_reconstruction(folder)
        gap = default_contact_gap(rec.report) if gap is None else gap
        region, source = analysed_domain(spec, rec.report, folder, rec.field_of_view)
        snap = _snapshot(rec, gap, options, region, source)
        tables = {"bubbles": snap.bubbles, "contacts": snap.contacts, "grid": snap.grid, "shells": snap.shells}
        summary = {"kind": "3d", "reconstruction": str(Path(folder)), "contact_gap_default": contact_gap is None,
                   **snap.summary}
        return Analysis("3d", tables, dict(SNAPSHOT_TABLES), summary)
    return _analyse_4d(Path(folder), gap, options, spec, progress)


def _subscans(folder):
    found = []
    for d in sorted(folder.iterdir()):
        if d.is_dir() and d.name.startswith("subscan_") and (d / "bubbles.ply").is_file():
            try:
                found.append((int(d.name[len("subscan_"):]), d))
            except ValueError:
                continue
    if not found:
        raise ValueError(f"{folder}: no complete subscan_NNNN folder with bubbles.ply")
    return found


def _time_unit(folder):
    report = folder / "report.json"
    if report.is_file():
        unit = _read_json(report).get("time_unit")
        if unit in ("s", "subscan"):
            return unit
    with open(folder / "tracks.csv", newline="") as fh:
        header = next(csv.reader(fh), [])
    return "s" if "time_s" in header else "subscan"


def _subscans_contact_gap(found):
    """The default contact gap of a 4D folder's subscans (``found``: ``(index, folder)``): that of the first
    report giving its preview's voxel, the cold start's (warm subscans are fitted without a preview), else
    the first subscan's (:func:`default_contact_gap`)."""
    reports = []
    for _, d in found:
        path = d / "report.json"
        reports.append(json.loads(path.read_text()) if path.is_file() else {})
    previewed = [r for r in reports if (r.get("preview") or {}).get("voxel_mm")]
    return default_contact_gap((previewed or reports)[0])


def _analyse_4d(folder, gap, options, spec, progress):
    default_gap = gap is None
    unit = _time_unit(folder)
    spec_columns = dynamics_columns(unit)
    t_col, t_info = spec_columns["rates"]["time"][0], spec_columns["rates"]["time"][1:]
    steps, per_table, summaries = [], {k: [] for k in SNAPSHOT_TABLES}, []
    found = _subscans(folder)
    if gap is None:
        gap = _subscans_contact_gap(found)
    recs = [read_reconstruction(d) for _, d in found]
    region, source = analysed_domain(spec, recs[0].report, found[0][1], recs[0].field_of_view)
    region, grid, shells = _fixed_regions(recs, region, options["grid"], options["shells"])
    if source.startswith("the bounding box"):
        source = "the bounding box of every subscan's bubbles (neither the sample nor the field of view is known)"
    options = {"grid": grid, "shells": shells}
    for n, ((index, d), rec) in enumerate(zip(found, recs)):
        time = float(rec.report.get("time", index))
        snap = _snapshot(rec, gap, options, region, source)
        for name in SNAPSHOT_TABLES:
            per_table[name] += [{"subscan": index, t_col: time, **r} for r in getattr(snap, name)]
        steps.append(snap.step(index, time))
        summaries.append({"subscan": index, "time": time,
                          **{k: v for k, v in snap.summary.items() if k not in ("domain", "grid", "shells")}})
        if progress:
            progress(f"subscan {index} ({n + 1} of {len(found)}): {snap.summary['bubbles']} bubbles, "
                     f"{snap.summary['contacts']} contacts")
    columns = {name: {"subscan": ("", "subscan index"), t_col: t_info, **info}
               for name, info in SNAPSHOT_TABLES.items()}
    rates = growth_rates(steps)
    whole = [r for r in rates if np.isfinite(r["two_thirds_rate"])]
    law = fit_growth_law([r["coordination"] for r in whole], [r["two_thirds_rate"] for r in whole])
    sizes, distribution = size_tables(steps)
    lineage = None
    if (folder / "lineage.csv").is_file():  # the reconstruction's own record of births, ends and coalescences
        with open(folder / "lineage.csv", newline="") as fh:
            lineage = list(csv.DictReader(fh))
    dyn = {"rates": rates, "t1": t1_events(steps), "events": track_events(steps, lineage), "sizes": sizes,
           "distribution": distribution}
    tables = dict(per_table)
    for name, rows in dyn.items():
        tables[name] = named_rows(rows, spec_columns[name])
        columns[name] = describe(spec_columns[name])
    kinds = [r["kind"] for r in dyn["events"]]
    summary = {"kind": "4d", "reconstruction": str(folder), "time_unit": unit, "contact_gap_mm": gap,
               "contact_gap_default": default_gap, "subscans": len(steps),
               "domain": {**region.describe(), "source": source}, "grid": list(grid), "shells": shells,
               "growth_law": {"model": f"d(V^(2/3))/dt = k (Z - Z0), k in mm^2/{unit}", **law},
               "t1_events": len(dyn["t1"]), "coalescences": kinds.count("coalescence"),
               "disappearances": kinds.count("disappearance"), "appearances": kinds.count("appearance"),
               "events_from": "lineage.csv, volumes where it names no bubble" if lineage is not None else "volumes",
               "per_subscan": summaries}
    return Analysis("4d", tables, columns, summary)
