"""Experiment folders: the output-folder policy (:mod:`bubsub.clients.pipeline.results.outputs`) for experiments.

One folder may collect several experiments (``docs/results`` holds fig1a,
fig1b, fig5, ... side by side), so the policy applies per experiment:

1. :func:`check_experiment_folder`, before any computation: an ``--out`` that
   names a file, lies under one or cannot be written is refused; so is a
   folder holding the results of another bubsub command (a reconstruction,
   a simulation) unless ``--overwrite``, and one holding this experiment's
   results unless ``--resume`` (continue them) or ``--overwrite`` (replace
   them).
2. The experiment writes its files atomically.
3. :func:`finish_experiment` removes the files of this experiment's earlier
   run that the new run did not write again, keeps the other experiments'
   files, and writes the folder's manifest
   (:data:`~bubsub.clients.pipeline.results.outputs.MANIFEST`, command
   ``"experiment"``, with the files of each experiment under
   ``"experiments"``).
"""

from __future__ import annotations

import json
from pathlib import Path

from bubsub.clients.pipeline.results.outputs import (
    MANIFEST,
    OutputFolderError,
    check_output_folder,
    earlier_outputs,
    finish_outputs,
)

__all__ = ["COMMAND", "experiment_files", "check_experiment_folder", "finish_experiment"]

#: The manifest's ``command`` for a folder of experiments.
COMMAND = "experiment"


def _manifest(folder):
    try:
        doc = json.loads((Path(folder) / MANIFEST).read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def _experiments(doc):
    """``{experiment name: [relative paths]}`` of an experiment folder's manifest (empty for other commands)."""
    if not doc or doc.get("command") != COMMAND or not isinstance(doc.get("experiments"), dict):
        return {}
    return {str(k): [str(f) for f in v] for k, v in doc["experiments"].items() if isinstance(v, list)}


def experiment_files(folder, name):
    """The files of experiment ``name`` in ``folder``: those its manifest lists, and ``NAME.*`` beside it.

    Returns
    -------
    list of pathlib.Path
        Existing files, sorted.
    """
    folder = Path(folder)
    listed = {folder / f for f in _experiments(_manifest(folder)).get(name, [])}
    own = set(folder.glob(f"{name}.*")) if folder.is_dir() else set()
    return sorted(p for p in listed | own if p.is_file())


def check_experiment_folder(path, name, *, overwrite=False, resume=False):
    """Step 1 of the policy for experiment ``name``: the folder, or a clear refusal.

    Parameters
    ----------
    path : str or os.PathLike
    name : str
        The experiment (``fig1a``, ``fig6``, ...).
    overwrite : bool
        Accept a folder holding this experiment's results or another command's (replaced at step 3).
    resume : bool
        Accept a folder holding this experiment's results (continued).

    Returns
    -------
    pathlib.Path

    Raises
    ------
    OutputFolderError
    """
    folder = check_output_folder(path, overwrite=True)  # a file, under a file, not writable: refused here
    doc = _manifest(folder)
    if not overwrite:
        other = doc.get("command") if doc and doc.get("command") != COMMAND else None
        foreign = [f for f in earlier_outputs(folder) if f.name != MANIFEST] if doc is None or other else []
        if other or foreign:
            what = f"bubsub {other}" if other else "another bubsub command"
            names = ", ".join(f.name for f in foreign[:4]) + (", ..." if len(foreign) > 4 else "")
            raise OutputFolderError(f"{str(path)!r} already holds the results of an earlier {what} run"
                                    f"{f' ({names})' if names else ''}; pass --overwrite to replace them, "
                                    f"or choose another --out")
        mine = experiment_files(folder, name)
        if mine and not resume:
            names = ", ".join(f.name for f in mine[:4]) + (", ..." if len(mine) > 4 else "")
            raise OutputFolderError(f"{str(path)!r} already holds results of experiment {name} ({names}); "
                                    f"pass --resume to continue them, --overwrite to replace them, "
                                    f"or choose another --out")
    return folder


def finish_experiment(path, name, files):
    """Step 3 of the policy: drop this experiment's earlier files not written again, write the manifest.

    Parameters
    ----------
    path : str or os.PathLike
    name : str
    files : iterable of str or os.PathLike
        The files this run of ``name`` wrote (or kept, when resumed).

    Returns
    -------
    list of pathlib.Path
        The earlier files removed.
    """
    folder = Path(path)
    root = folder.resolve()
    runs = _experiments(_manifest(folder))
    runs[name] = sorted(str(Path(f).resolve().relative_to(root)) for f in files)
    keep = [folder / f for other, fs in runs.items() if other != name for f in fs if (folder / f).is_file()]
    runs = {k: [f for f in v if (folder / f).is_file()] for k, v in runs.items()}
    return finish_outputs(folder, [*keep, *(folder / f for f in runs[name])], command=COMMAND,
                          experiments=dict(sorted(runs.items())))
