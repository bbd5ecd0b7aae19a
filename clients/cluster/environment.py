"""The environment that holds a task's threads: read by the engine (embedded clusters), the worker
plugin (existing clusters) and the batch-script helper (:mod:`.hpc`)."""

from __future__ import annotations

__all__ = ["pinned_environment"]


def pinned_environment(threads):
    """Environment variables that hold one task's projector, numba and BLAS threads to ``threads``.

    Parameters
    ----------
    threads : int

    Returns
    -------
    dict of str to str
        ``BUBSUB_THREADS``, ``NUMBA_NUM_THREADS``, ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``,
        ``MKL_NUM_THREADS``, each ``str(threads)``.
    """
    n = str(int(threads))
    return {"BUBSUB_THREADS": n, "NUMBA_NUM_THREADS": n, "OMP_NUM_THREADS": n, "OPENBLAS_NUM_THREADS": n,
            "MKL_NUM_THREADS": n}
