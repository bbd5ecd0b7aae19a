#!/bin/sh
# A small bubsub run on a Dask cluster: the cluster-client service of docker/docker-compose.yml.
#   DASK_SCHEDULER_ADDRESS=tcp://HOST:8786 sh examples/cluster_run.sh OUT
# The tasks (one per setting, seed and method) run on the workers; OUT must be on a filesystem the
# client can write (the workers return their results through the scheduler).
set -eu
out="${1:-cluster-example}"
bubsub experiment fig5 --quick --values 0.5 1.0 --methods bubsub --out "$out" --quiet
python - "$out" <<'PY'
import csv, sys
rows = list(csv.DictReader(open(f"{sys.argv[1]}/fig5.csv")))
assert len(rows) == 2 and all(0 <= float(r["ddi"]) < 0.2 for r in rows), rows
print(f"cluster run: {len(rows)} tasks, DDI", ", ".join(f"{float(r['ddi']):.4f}" for r in rows))
PY
