"""A paper experiment on a SLURM cluster through dask-jobqueue (needs the 'cluster' extra).

Run on a login node, in the environment where bubsub is installed (the jobs use the same
Python, so the environment must be on a filesystem the compute nodes see):

    python examples/slurm_experiment.py --out results/fig1a --jobs 4 --queue short --account foam

Each SLURM job starts --workers-per-job Dask workers with 1 thread each; one task is one
(setting, seed, method) case of the experiment. Print the batch script without submitting
anything with --dry-run.
"""

import argparse

from bubsub.clients.cluster.hpc import slurm_cluster

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--experiment", default="fig1a", choices=("fig1a", "fig1b", "fig5", "fig3a"))
ap.add_argument("--out", required=True)
ap.add_argument("--jobs", type=int, default=4, help="SLURM jobs (each one node share)")
ap.add_argument("--workers-per-job", type=int, default=8)
ap.add_argument("--memory", default="32GB", help="per job")
ap.add_argument("--walltime", default="04:00:00")
ap.add_argument("--queue")
ap.add_argument("--account")
ap.add_argument("--interface", help="network interface the workers reach the scheduler on, e.g. ib0")
ap.add_argument("--quick", action="store_true")
ap.add_argument("--dry-run", action="store_true", help="print the job script and stop")
args = ap.parse_args()

cluster = slurm_cluster(workers_per_job=args.workers_per_job, memory=args.memory, walltime=args.walltime,
                        queue=args.queue, account=args.account, log_directory="dask-logs",
                        **({"interface": args.interface} if args.interface else {}))
try:
    print(cluster.job_script())
    if not args.dry_run:
        from dask.distributed import Client

        from bubsub.clients.experiments.runner import run_experiment

        cluster.scale(jobs=args.jobs)
        with Client(cluster) as client:
            # --resume: a run cut short by the walltime continues where it stopped
            run_experiment(args.experiment, args.out, quick=args.quick, resume=True, client=client)
finally:
    cluster.close()
