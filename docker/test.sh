#!/usr/bin/env bash
# `make docker-test`: build the image, bring the compose project up (ports on 127.0.0.1 only), run
# both example clients to completion, check every service's health, tear everything down.
# Needs a Docker engine and docker-compose (v1 or v2); not part of `make test`.
set -euo pipefail
cd "$(dirname "$0")/.."
IMAGE=bubsub:latest
PROJECT=${BUBSUB_COMPOSE_PROJECT:-bubsubtest}
if docker compose version >/dev/null 2>&1; then COMPOSE=(docker compose); else COMPOSE=(docker-compose); fi
COMPOSE+=(-f docker/docker-compose.yml -p "$PROJECT")
step() { printf '\n== %s (%ss)\n' "$*" "$SECONDS"; }
free_port() { python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
# free host ports, so that a server or dashboard already running here does not stop the test
export BUBSUB_HOST_PORT=${BUBSUB_HOST_PORT:-$(free_port)} DASK_DASHBOARD_HOST_PORT=${DASK_DASHBOARD_HOST_PORT:-$(free_port)}

step "build $IMAGE (classic builder, --network host)"
docker build --network host -f docker/Dockerfile -t "$IMAGE" . | grep -E '^(Step|Successfully)' || exit 1
docker image inspect "$IMAGE" --format 'image size: {{.Size}} bytes; user {{.Config.User}}; cmd {{.Config.Cmd}}'

cleanup() {
  step "tear down"
  "${COMPOSE[@]}" down -v --remove-orphans 2>&1 | tail -n 3 || true
  left=$(docker ps -aq --filter "label=com.docker.compose.project=$PROJECT")
  [ -z "$left" ] && echo "no containers left" || { echo "containers left: $left"; exit 1; }
}
trap cleanup EXIT

step "compose up: projector, scheduler, workers"
"${COMPOSE[@]}" config -q
"${COMPOSE[@]}" up -d --no-build projector scheduler worker 2>&1 | tail -n 6

wait_healthy() {  # every container of the project except the one-off clients
  local end=$((SECONDS + 180)) ids states
  while :; do
    ids=$(docker ps -q --filter "label=com.docker.compose.project=$PROJECT" --filter "label=com.docker.compose.oneoff=False")
    states=$(docker inspect --format '{{.Name}} {{.State.Health.Status}}' $ids)
    if ! grep -qv ' healthy$' <<<"$states"; then echo "$states"; return 0; fi
    if ((SECONDS > end)); then echo "$states"; "${COMPOSE[@]}" logs --tail 30; return 1; fi
    sleep 2
  done
}
step "health of every service"
wait_healthy
n=$(docker ps -q --filter "label=com.docker.compose.project=$PROJECT" --filter "label=com.docker.compose.service=worker" | wc -l)
[ "$n" -ge 2 ] || { echo "expected 2 workers, found $n"; exit 1; }

step "published ports are bound to 127.0.0.1 only"
docker ps --filter "label=com.docker.compose.project=$PROJECT" --format '{{.Names}} {{.Ports}}'
if docker ps --filter "label=com.docker.compose.project=$PROJECT" --format '{{.Ports}}' | grep -E '(0\.0\.0\.0|:::)[0-9]*->'; then
  echo "a port is published on all interfaces"; exit 1
fi
python3 - "$BUBSUB_HOST_PORT" "$DASK_DASHBOARD_HOST_PORT" <<'PY'
import json, sys, urllib.request
with urllib.request.urlopen(f"http://127.0.0.1:{sys.argv[1]}/healthz", timeout=5) as r:
    print("projector /healthz from the host:", r.status, json.load(r))
with urllib.request.urlopen(f"http://127.0.0.1:{sys.argv[2]}/health", timeout=5) as r:
    print("scheduler /health from the host:", r.status, r.read().decode())
PY

step "example client: a fit on the projection server"
"${COMPOSE[@]}" run --rm --no-deps client 2>&1 | tail -n 8

step "example cluster client: a run on the Dask workers"
"${COMPOSE[@]}" run --rm --no-deps cluster-client 2>&1 | tail -n 12
errors=$("${COMPOSE[@]}" logs --no-color worker 2>&1 | grep -ciE 'error|traceback' || true)
echo "worker log lines with errors: $errors"

step "health after the runs"
wait_healthy
step "docker-test passed"
