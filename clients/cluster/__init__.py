"""Running bubsub's independent tasks on a Dask cluster, or in-process.

A run is described by a :class:`ClusterSpec` (``in_process()``, ``local(n)``,
``remote(address)``, ``from_scheduler_file(path)``, or ``spec_from_options``
for the ``--workers/--scheduler/--scheduler-file`` options and the
``DASK_SCHEDULER_ADDRESS`` variable). :func:`open_client` turns it into a
``dask.distributed.Client`` (or ``None`` in-process) and :func:`run_tasks`
maps a picklable function over task arguments with either. Dask is imported
only when a cluster is asked for; it comes with the ``cluster`` extra
(``pip install 'bubsub[cluster]'``).
"""

from bubsub.clients.cluster.engine import (ClusterSpec, from_scheduler_file, in_process, local, open_client, remote,
                                           run_tasks, spec_from_options)

__all__ = ["ClusterSpec", "in_process", "local", "remote", "from_scheduler_file", "spec_from_options", "open_client",
           "run_tasks"]
