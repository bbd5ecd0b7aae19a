"""Where bubsub's tasks run: in-process, on an embedded ``LocalCluster`` or on an existing Dask cluster.

The unit of distribution is a whole fit (one experiment case, one subscan),
never one objective evaluation: a task round trip costs milliseconds, a fit
seconds to minutes. Task functions are module-level and picklable; they read
their inputs (scan files on a shared filesystem, seeds) themselves rather
than having arrays shipped through the scheduler, and return small results
(meshes, numbers), never projector or Embree objects.

Dask (``dask.distributed``) is imported only inside :func:`open_client` and
only when a cluster is asked for; without one everything runs in this
process, in task order.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from dataclasses import dataclass

from bubsub.core.validate import check_int

from bubsub.clients.cluster.environment import pinned_environment

__all__ = ["ClusterSpec", "in_process", "local", "remote", "from_scheduler_file", "spec_from_options", "open_client",
           "run_tasks", "workers_of", "distributed"]

#: what ``import dask.distributed`` failing tells the user
_INSTALL_HINT = "running on a Dask cluster needs the 'cluster' extra: pip install 'bubsub[cluster]'"


@dataclass(frozen=True)
class ClusterSpec:
    """Where to run: nothing set means in-process.

    Attributes
    ----------
    workers : int or None
        Worker processes of an embedded ``LocalCluster`` (on 127.0.0.1).
    scheduler : str or None
        Address of an existing scheduler, ``tcp://HOST:PORT``.
    scheduler_file : str or None
        Path of the JSON file a ``dask scheduler --scheduler-file`` wrote.
    threads : int
        Threads each worker gives to one task (projector, numba, BLAS), and
        task slots per embedded worker.
    dashboard : bool
        Serve the embedded cluster's dashboard (on a free port of 127.0.0.1).
    """

    workers: int | None = None
    scheduler: str | None = None
    scheduler_file: str | None = None
    threads: int = 1
    dashboard: bool = False

    @property
    def in_process(self):
        return self.workers is None and self.scheduler is None and self.scheduler_file is None

    @property
    def kind(self):
        """``"in-process"``, ``"local"`` (embedded LocalCluster) or ``"remote"``."""
        return "in-process" if self.in_process else ("local" if self.workers is not None else "remote")

    def __repr__(self):
        if self.in_process:
            return "in_process()"
        if self.workers is not None:
            extra = "".join([f", threads={self.threads}" if self.threads != 1 else "",
                             ", dashboard=True" if self.dashboard else ""])
            return f"local({self.workers}{extra})"
        if self.scheduler is not None:
            return f"remote({self.scheduler!r})"
        return f"from_scheduler_file({self.scheduler_file!r})"


def in_process():
    """Run every task here, one after the other, without Dask."""
    return ClusterSpec()


def local(workers, threads=1, dashboard=False):
    """An embedded ``LocalCluster`` of ``workers`` processes on 127.0.0.1, torn down after the run."""
    check_int(workers, "workers", 1)
    check_int(threads, "threads", 1)
    return ClusterSpec(workers=workers, threads=threads, dashboard=bool(dashboard))


def remote(address):
    """An existing cluster's scheduler at ``tcp://HOST:PORT`` (or ``tls://``, ``ws://``...)."""
    if not isinstance(address, str) or "://" not in address:
        raise ValueError(f"a scheduler address looks like tcp://HOST:PORT, got {address!r}")
    return ClusterSpec(scheduler=address)


def from_scheduler_file(path):
    """An existing cluster whose scheduler wrote ``path`` (``dask scheduler --scheduler-file``)."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"scheduler file {path} does not exist (start `dask scheduler --scheduler-file {path}` first)")
    return ClusterSpec(scheduler_file=path)


def spec_from_options(workers=None, scheduler=None, scheduler_file=None, dashboard=False, environ=None):
    """The :class:`ClusterSpec` of the command-line options, else of ``DASK_SCHEDULER_ADDRESS``, else in-process.

    At most one of ``workers``, ``scheduler`` and ``scheduler_file`` may be given.
    """
    given = [name for name, v in (("--workers", workers), ("--scheduler", scheduler),
                                  ("--scheduler-file", scheduler_file)) if v is not None]
    if len(given) > 1:
        raise ValueError(f"give only one of {', '.join(given)}")
    if dashboard and workers is None:
        raise ValueError("--dashboard is for the embedded cluster of --workers N; an existing cluster has its own")
    if workers is not None:
        return local(workers, dashboard=dashboard)
    if scheduler is not None:
        return remote(scheduler)
    if scheduler_file is not None:
        return from_scheduler_file(scheduler_file)
    address = (os.environ if environ is None else environ).get("DASK_SCHEDULER_ADDRESS", "").strip()
    return remote(address) if address else in_process()


def distributed():
    """The ``dask.distributed`` module; an ImportError naming the ``cluster`` extra when it is missing."""
    try:
        import dask.distributed as dd
    except ImportError as exc:
        raise ImportError(_INSTALL_HINT) from exc
    return dd


@contextmanager
def open_client(spec):
    """A ``dask.distributed.Client`` for ``spec`` (``None`` in-process); closed, and an embedded cluster stopped, on exit."""
    if spec.in_process:
        yield None
        return
    dd = distributed()
    from bubsub.clients.cluster.worker import PinThreads

    cluster = None
    if spec.workers is not None:
        cluster = dd.LocalCluster(n_workers=spec.workers, threads_per_worker=spec.threads, processes=True,
                                  host="127.0.0.1", dashboard_address="127.0.0.1:0" if spec.dashboard else None,
                                  env=pinned_environment(spec.threads))
        client = dd.Client(cluster)
    elif spec.scheduler is not None:
        client = dd.Client(spec.scheduler, timeout="30s")
    else:
        client = dd.Client(scheduler_file=spec.scheduler_file, timeout="30s")
    try:
        # workers of an existing cluster were started by someone else: pin their threads here too
        client.register_plugin(PinThreads(spec.threads), name="bubsub-pin-threads")
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def workers_of(client):
    """How many workers ``client``'s cluster has now (0 in-process)."""
    return 0 if client is None else len(client.scheduler_info()["workers"])


def run_tasks(client, fn, tasks, *, on_result=None, retries=2):
    """``[fn(*args) for args in tasks]``, here (``client=None``) or on ``client``'s cluster.

    Parameters
    ----------
    client : dask.distributed.Client or None
    fn : callable
        Module-level (picklable) function.
    tasks : sequence of tuple
        The arguments of each call.
    on_result : callable, optional
        ``on_result(index, result)`` as each task finishes (in completion
        order on a cluster), e.g. to write it out or advance a progress bar.
    retries : int
        Times a task that raised on a worker is tried again; a task lost with
        its worker is rescheduled by Dask itself.

    Returns
    -------
    list
        The results, in the order of ``tasks``. A task's exception is raised
        here; Ctrl-C or an error cancels the tasks not yet finished.
    """
    tasks = list(tasks)
    results = [None] * len(tasks)
    if client is None:
        for i, args in enumerate(tasks):
            results[i] = fn(*args)
            if on_result is not None:
                on_result(i, results[i])
        return results
    dd = distributed()
    futures = [client.submit(fn, *args, pure=False, retries=retries) for args in tasks]
    index = {f.key: i for i, f in enumerate(futures)}
    try:
        for future in dd.as_completed(futures):
            i = index[future.key]
            results[i] = future.result()
            if on_result is not None:
                on_result(i, results[i])
    finally:
        client.cancel([f for f in futures if not f.done()])
    return results
