"""Output folders: the one policy every bubsub command that writes results follows, and the files of
``bubsub reconstruct`` (:func:`write_outputs`).

A folder *holds bubsub results* when it has the manifest :data:`MANIFEST`
(written last by :func:`finish_outputs`, listing the files of that run) or,
for folders written before the manifest existed, any of :data:`RESULT_NAMES`.

The policy
----------
1. Before any computation, :func:`check_output_folder` refuses an ``--out``
   that names a file, lies under a file or cannot be written, and a folder
   that holds bubsub results unless ``overwrite`` (``--overwrite``) is given;
   the message names the flag.
2. The command writes its files (atomically, :mod:`bubsub.core.io.atomic`).
3. :func:`finish_outputs` removes every file of the earlier run that the new
   run did not replace (so a 3D run never leaves a 2D run's ``bubbles.json``
   beside its ``bubbles.ply``) and writes the new manifest.

An interrupted or failed run leaves the earlier results as they were until
step 3. A new command adds ``--out``/``--overwrite`` with
:func:`bubsub.clients.cli.args.add_output_arguments` and calls steps 1 and 3::

    out = check_output_folder(args.out, overwrite=args.overwrite)  # step 1, in the first second
    files = [...]                                                   # step 2: paths it wrote
    finish_outputs(out, files, command="reconstruct4d")             # step 3
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from bubsub.core.io.atomic import atomic_path, atomic_write_text
from bubsub.core.io.meshio import write_ply, write_polygons_json
from bubsub.core.io.tables import BUBBLE_COLUMN_INFO, BUBBLE_COLUMNS_2D, BUBBLE_COLUMNS_3D, csv_metadata_path, write_csv
from bubsub.core.analysis.shape import bubble_table

from bubsub.clients.pipeline.results.figures import write_figures
from bubsub.clients.pipeline.inputs.fov import FOV_COLUMN_INFO, fov_columns
from bubsub.clients import version

__all__ = ["write_outputs", "json_default", "MANIFEST", "RESULT_NAMES", "OutputFolderError", "folder_problem",
           "earlier_outputs", "check_output_folder", "finish_outputs", "add_outputs"]

#: Name of the manifest: ``{"bubsub": version, "command": str, "files": [relative paths]}``.
MANIFEST = "bubsub-outputs.json"

#: Files bubsub wrote before the manifest existed; a folder holding one of them holds results.
RESULT_NAMES = frozenset({
    "report.json", "bubbles.ply", "bubbles.json", "bubbles.csv", "control.ply", "control.json",
    "overlay.png", "scan.h5", "truth.json", "truth.ply", "phantom.json", "ddi.txt", "demo.png",
})


class OutputFolderError(ValueError):
    """An output folder the policy refuses (``bubsub`` prints it as one line, exit status 2)."""


def folder_problem(path):
    """Why ``path`` cannot be an output folder (a file, under a file, not writable), or None.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    str or None
    """
    p = Path(path)
    if str(path) == "":
        return "the output folder name is empty"
    if p.exists() and not p.is_dir():
        return f"{str(p)!r} is a file, not a folder; give --out a folder name"
    ancestor = p
    while not ancestor.exists():
        if ancestor.parent == ancestor:
            break
        ancestor = ancestor.parent
    if ancestor.exists() and not ancestor.is_dir():
        return f"cannot create the folder {str(p)!r}: {str(ancestor)!r} is a file"
    if ancestor.exists() and not os.access(ancestor, os.W_OK | os.X_OK):
        return f"cannot write into {str(ancestor)!r} (permission denied); choose another --out"
    return None


def _manifest(folder):
    m = folder / MANIFEST
    if not m.is_file():
        return None
    try:
        doc = json.loads(m.read_text())
        return doc if isinstance(doc, dict) and isinstance(doc.get("files"), list) else None
    except (OSError, ValueError):
        return None


def earlier_outputs(path):
    """The files of an earlier bubsub run in ``path`` (manifest entries and legacy names).

    Returns
    -------
    list of pathlib.Path
        Existing files, sorted; empty when the folder holds no bubsub results.
    """
    folder = Path(path)
    if not folder.is_dir():
        return []
    found = {folder / n for n in RESULT_NAMES if (folder / n).is_file()}
    doc = _manifest(folder)
    if doc is not None:
        for name in doc["files"]:
            f = (folder / str(name)).resolve()
            # never follow a manifest outside its own folder
            if folder.resolve() in f.parents and f.is_file():
                found.add(folder / str(name))
    if (folder / MANIFEST).is_file():
        found.add(folder / MANIFEST)
    return sorted(found)


def check_output_folder(path, *, overwrite=False):
    """Step 1 of the policy: the output folder, refused with a clear message if it is unusable.

    Parameters
    ----------
    path : str or os.PathLike
    overwrite : bool
        Accept a folder holding earlier bubsub results (they are replaced by
        :func:`finish_outputs`).

    Returns
    -------
    pathlib.Path
        Not created yet (nothing is written before the computation succeeds).

    Raises
    ------
    OutputFolderError
    """
    problem = folder_problem(path)
    if problem:
        raise OutputFolderError(problem)
    earlier = earlier_outputs(path)
    if earlier and not overwrite:
        doc = _manifest(Path(path))
        what = f"bubsub {doc['command']}" if doc and doc.get("command") else "bubsub"
        names = ", ".join(f.name for f in earlier[:4]) + (", ..." if len(earlier) > 4 else "")
        raise OutputFolderError(
            f"{str(path)!r} already holds the results of an earlier {what} run ({names}); "
            f"pass --overwrite to replace them, or choose another --out")
    return Path(path)


def finish_outputs(path, files, command, **info):
    """Step 3 of the policy: remove the earlier run's files not written again, then write the manifest.

    Parameters
    ----------
    path : str or os.PathLike
        The output folder.
    files : iterable of str or os.PathLike
        The files this run wrote, as opened (e.g. ``folder / "bubbles.csv"``).
    command : str
        E.g. ``"reconstruct"``; named in later refusals.
    **info
        Extra JSON-able entries for the manifest.

    Returns
    -------
    list of pathlib.Path
        The earlier files removed.
    """
    folder = Path(path)
    written = {Path(f).resolve() for f in files}
    removed = []
    for old in earlier_outputs(folder):
        if old.name != MANIFEST and old.resolve() not in written:
            old.unlink(missing_ok=True)
            removed.append(old)

    names = sorted(os.path.relpath(f, folder.resolve()) for f in written)
    doc = {"bubsub": version(), "command": command, "files": names, **info}
    atomic_write_text(folder / MANIFEST, json.dumps(doc, indent=2) + "\n")
    return removed


def json_default(o):
    """``json.dumps(..., default=json_default)``: numpy scalars and arrays as numbers and lists, anything
    else as its ``str``."""
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def write_outputs(out_dir, rec, scan_path=None, *, progress=False):
    """Write ``bubbles.ply|json``, ``control.ply|json``, ``bubbles.csv`` and its column sidecar,
    ``report.json`` and the pictures of :func:`write_figures`.

    Every file goes to a temporary name first and is renamed when complete;
    then the files of an earlier run in ``out_dir`` that were not replaced are
    removed (:func:`finish_outputs`). Callers that must not replace earlier
    results check the folder first (:func:`check_output_folder`).

    Parameters
    ----------
    out_dir : str or os.PathLike
        Created if missing.
    rec : bubsub.clients.pipeline.reconstruct.Reconstruction
        Its ``files`` is set to the returned mapping.
    scan_path : str or os.PathLike, optional
        Recorded in ``report.json``.
    progress : bool
        Show the pictures as a phase (seconds for 3D meshes).

    Returns
    -------
    dict of str to pathlib.Path
        ``{"mesh", "control", "table", "table_columns", "overlay", "sizes", ["meshes",] "report"}``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fine = [s.fine() for s in rec.surfaces]
    files = {}
    if rec.report["dimension"] == 3:
        files["mesh"] = out / "bubbles.ply"
        write_ply(files["mesh"], [s.fine() for s in rec.surfaces], rec.ids)
        files["control"] = out / "control.ply"
        write_ply(files["control"], [s.control for s in rec.surfaces], rec.ids)
    else:
        files["mesh"] = out / "bubbles.json"
        write_polygons_json(files["mesh"], fine, rec.ids)
        files["control"] = out / "control.json"
        write_polygons_json(files["control"], [s.control for s in rec.surfaces], rec.ids)
    files["table"] = out / "bubbles.csv"
    rows = bubble_table(fine, rec.ids)
    columns = BUBBLE_COLUMNS_3D if rec.report["dimension"] == 3 else BUBBLE_COLUMNS_2D
    info = BUBBLE_COLUMN_INFO
    if rec.report.get("field_of_view_mm") is not None and fine:
        # bubbles cut by the edge of the field of view are flagged, not dropped; their whole size is left empty
        columns = (*columns, *fov_columns(rows, fine, rec.report))
        info = {**info, **FOV_COLUMN_INFO}
    write_csv(files["table"], rows, columns,
              describe=info, title="bubbles reconstructed by bubsub reconstruct")
    files["table_columns"] = csv_metadata_path(files["table"])
    report = dict(rec.report)
    if scan_path is not None:
        report["scan"] = str(scan_path)
    files.update(write_figures(out, rec, fine, rows, progress=progress))
    report["files"] = {k: v.name for k, v in files.items()}
    files["report"] = out / "report.json"
    with atomic_path(files["report"]) as tmp:
        Path(tmp).write_text(json.dumps(report, indent=2, default=json_default))
    rec.files = files
    finish_outputs(out, files.values(), command="reconstruct")
    return files


def add_outputs(path, files, command):
    """Add files that a later command wrote into an existing result folder (``bubsub evaluate``'s
    ``evaluation.json``) to the folder's manifest, so that the next ``--overwrite`` run into the folder
    removes them with the rest (step 3 of the policy).

    Parameters
    ----------
    path : str or os.PathLike
        The result folder.
    files : iterable of str or os.PathLike
        The files written, inside ``path``.
    command : str
        Recorded as the manifest's command when the folder has none yet.
    """
    folder = Path(path)
    doc = _manifest(folder)
    if doc is None:
        doc = {"bubsub": version(), "command": command, "files": []}
    names = set(doc["files"]) | {os.path.relpath(Path(f).resolve(), folder.resolve()) for f in files}
    doc["files"] = sorted(names)
    atomic_write_text(folder / MANIFEST, json.dumps(doc, indent=2) + "\n")
