"""What each phase of a reconstruction cost and where its projections ran, for ``report.json``.

:class:`PhaseClock` times the phases of
:func:`~bubsub.clients.pipeline.reconstruct.reconstruct` (``seconds_parts``,
``cpu_seconds_parts``); :func:`projector_report` says which of them
projected on a remote server (``projector``), and
:func:`merged_projector_report` merges the slabs' reports into one.
"""

from __future__ import annotations

import time

from bubsub.core.malloc import release_free_memory

__all__ = ["PhaseClock", "REMOTE_PHASES", "projector_report", "merged_projector_report"]


class PhaseClock:
    """Wall and CPU seconds (this process, all threads) of consecutive phases, for ``report.json``."""

    def __init__(self):
        self._start = self._wall = time.perf_counter()
        self._cpu = time.process_time()
        self._parts = {}

    def mark(self, name):
        """End the phase ``name`` now (added to its earlier time when it ran before); the next one starts
        (with the phase's freed memory given back: :func:`bubsub.core.malloc.release_free_memory`)."""
        release_free_memory()
        wall, cpu = time.perf_counter(), time.process_time()
        w0, c0 = self._parts.get(name, (0.0, 0.0))
        self._parts[name] = (w0 + wall - self._wall, c0 + cpu - self._cpu)
        self._wall, self._cpu = wall, cpu

    def elapsed(self):
        """Wall seconds since the clock was made."""
        return time.perf_counter() - self._start

    def parts(self):
        """``({phase: wall seconds}, {phase: CPU seconds})``."""
        return {k: w for k, (w, _) in self._parts.items()}, {k: c for k, (_, c) in self._parts.items()}


#: the phases of :func:`reconstruct` that project through ``projector_factory``'s projectors (the initial
#: objective and every level of the fit); the others project with local ones
REMOTE_PHASES = ("fit",)


def projector_report(remote, phases, backend):
    """``report.json``'s ``projector``: where the projections of each phase ran.

    Parameters
    ----------
    remote : object or None
        The projector ``projector_factory`` made (a
        :class:`~bubsub.clients.remote.client.RemoteJob` says its ``server``); None when every
        phase projected locally.
    phases : iterable of str
        The phases that ran, in order (``seconds_parts``' keys).
    backend : str
        The local projectors' backend.

    Returns
    -------
    dict
        ``server`` (URL or None), ``remote_phases``, ``local_phases`` (lists of phase names) and
        ``local_backend``.
    """
    phases = list(phases)
    remote_phases = [p for p in phases if p in REMOTE_PHASES] if remote is not None else []
    return {"server": getattr(remote, "server", None) if remote is not None else None,
            "remote_phases": remote_phases, "local_phases": [p for p in phases if p not in remote_phases],
            "local_backend": backend}


def merged_projector_report(reports):
    """One :func:`projector_report` for several runs' (the slabs of a scan): the first server named, and
    the phases that ran remotely in any run, or locally in any, in the order they first appear; None
    when no run has one."""
    reports = [r for r in reports if r]
    if not reports:
        return None
    remote, local = [], []
    for r in reports:
        remote += [p for p in r["remote_phases"] if p not in remote]
        local += [p for p in r["local_phases"] if p not in local]
    return {"server": next((r["server"] for r in reports if r["server"]), None), "remote_phases": remote,
            "local_phases": local, "local_backend": reports[0]["local_backend"]}
