"""Worker-side setup, imported only where ``dask.distributed`` is installed."""

from __future__ import annotations

import os

from distributed.diagnostics.plugin import WorkerPlugin

from bubsub.clients.cluster.environment import pinned_environment

__all__ = ["PinThreads"]


class PinThreads(WorkerPlugin):
    """Hold each worker's projector, numba and BLAS threads to ``threads``.

    An embedded cluster gets the same variables at process start; workers of
    an existing cluster get them here, before their first bubsub task (the
    projector reads ``BUBSUB_THREADS`` when it is made, BLAS is limited now).
    """

    def __init__(self, threads=1):
        self.threads = int(threads)

    def __repr__(self):
        return f"PinThreads({self.threads})"

    def setup(self, worker):
        os.environ.update(pinned_environment(self.threads))
        try:
            from threadpoolctl import threadpool_limits
        except ImportError:  # pragma: no cover - a dependency of bubsub
            return
        threadpool_limits(self.threads)
