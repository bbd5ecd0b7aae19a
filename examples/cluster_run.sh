#!/bin/sh
# A small 4D reconstruction on a Dask cluster: the cluster-client service of docker/docker-compose.yml.
#   DASK_SCHEDULER_ADDRESS=tcp://HOST:8786 sh examples/cluster_run.sh DIR
# DIR must be on a filesystem the workers see at the same path (they read the scan file from it).
# The chain of 4 subscans runs as one task per subscan, in 2 chunks linked at their shared subscan.
set -eu
dir="${1:-cluster-example}"
rm -rf "$dir/sim" "$dir/rec"
bubsub simulate --phantom expanding2d --bubbles 6 --det-count 240 --subscans 4 --projections-per-subscan 16 \
    --seed 5 --out "$dir/sim" >/dev/null
bubsub reconstruct4d "$dir/sim/scan.h5" --out "$dir/rec" --holdout odd --iterations 30 --chunks 2 --quiet
python - "$dir" <<'PY'
import json, sys
from bubsub.clients.pipeline.evaluation.evaluate4d import evaluate_dynamic
d = sys.argv[1]
r = json.load(open(f"{d}/rec/report.json"))
s = evaluate_dynamic(f"{d}/rec", f"{d}/sim")
print(f"engine {r['engine']}, {r['workers']} workers, {r['chunks']} chunks, links {r['chunk_links']}")
print(f"mean DDI {s['mean_ddi']:.4f}, rows on the right track {s['right_track_fraction']:.2f}")
assert r["engine"] == "dask" and r["subscans_complete"] == 4 and s["right_track_fraction"] == 1.0, (r, s)
PY
