"""Dask clusters on HPC batch systems (SLURM) through dask-jobqueue.

``slurm_cluster(...)`` returns a ``dask_jobqueue.SLURMCluster`` whose batch jobs
each start ``workers_per_job`` Dask workers with bubsub's projector, numba and
BLAS threads pinned (:func:`bubsub.clients.cluster.environment.pinned_environment`).
Scale it (``cluster.scale(jobs=4)`` or ``cluster.adapt(maximum_jobs=8)``) and
pass ``dask.distributed.Client(cluster)`` as the ``client`` of a run. The
script each job runs is ``cluster.job_script()``; see docs/cluster.md.
"""

from __future__ import annotations

from bubsub.core.validate import check_int

from bubsub.clients.cluster.environment import pinned_environment

__all__ = ["slurm_cluster"]


def slurm_cluster(*, workers_per_job=1, threads=1, memory="8GB", walltime="04:00:00", queue=None, account=None,
                  prologue=(), directives=(), log_directory=None, **kwargs):
    """A ``dask_jobqueue.SLURMCluster`` of bubsub workers (no jobs submitted until it is scaled).

    Parameters
    ----------
    workers_per_job : int
        Dask worker processes per SLURM job (one task each at a time).
    threads : int
        Threads per worker (``--cpus-per-task`` is ``workers_per_job * threads``).
    memory : str
        Memory per job (``#SBATCH --mem``), shared by its workers.
    walltime : str
        ``HH:MM:SS`` per job (``#SBATCH -t``); workers end with their job.
    queue, account : str, optional
        SLURM partition (``-p``) and account (``-A``).
    prologue : sequence of str
        Shell lines run before the workers start (``module load ...``,
        ``source venv/bin/activate``), after the thread pinning exports.
    directives : sequence of str
        Extra ``#SBATCH`` options, e.g. ``"--constraint=cpu"``.
    log_directory : str, optional
        Where the jobs' stdout/stderr go.
    **kwargs
        Passed on to ``SLURMCluster`` (``interface="ib0"``, ``scheduler_options``...).
    """
    try:
        from dask_jobqueue import SLURMCluster
    except ImportError as exc:
        raise ImportError("SLURM clusters need dask-jobqueue, part of the 'cluster' extra: "
                          "pip install 'bubsub[cluster]'") from exc
    for name, v in (("workers_per_job", workers_per_job), ("threads", threads)):
        check_int(v, name, 1)
    exports = [f"export {k}={v}" for k, v in pinned_environment(threads).items()]
    return SLURMCluster(cores=workers_per_job * threads, processes=workers_per_job, memory=memory, walltime=walltime,
                        queue=queue, account=account, job_script_prologue=[*exports, *prologue],
                        job_extra_directives=list(directives), log_directory=log_directory, **kwargs)
