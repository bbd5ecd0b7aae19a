# %% [markdown]
# # A BubSub fit on a projection server
#
# The optimiser runs here; every objective evaluation (projection of the
# subdivided bubbles, and its gradient) runs on a bubsub projection server.
# Swapping the local `MeshProjector` for a `RemoteJob` is the only change.
#
# Server: `--server URL`, else `$BUBSUB_SERVER`, else one is started here
# (`python -m bubsub.service` on a free local port). Token: `--token` or
# `$BUBSUB_TOKEN`.
#
#     python examples/remote_fit.py --server http://127.0.0.1:8000

# %%
import argparse
import os
import socket
import subprocess
import sys
import time

import numpy as np

from bubsub.clients.remote.client import ProjectorClient
from bubsub.clients.optimise.fit import fit
from bubsub.core import circle_surface
from bubsub.core.foam.phantoms import foam2d
from bubsub.core.foam.simulate import default_geometry_2d, simulate_2d

ap = argparse.ArgumentParser(description="Fit a small simulated 2D foam on a bubsub projection server.")
ap.add_argument("--server", default=os.environ.get("BUBSUB_SERVER"), help="server URL (default: $BUBSUB_SERVER)")
ap.add_argument("--token", default=os.environ.get("BUBSUB_TOKEN") or None, help="bearer token")
ap.add_argument("--bubbles", type=int, default=6)
ap.add_argument("--iterations", type=int, default=60)
ap.add_argument("--seed", type=int, default=3)
args, _ = ap.parse_known_args()  # notebook kernels pass their own arguments

# %% [markdown]
# ## The server

# %%
server_process = None
if not args.server:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server_process = subprocess.Popen([sys.executable, "-m", "bubsub.service", "--port", str(port),
                                       "--log-level", "warning"])
    args.server = f"http://127.0.0.1:{port}"
client = ProjectorClient(args.server, token=args.token)
client.wait_ready(60)
print(f"server {args.server} is ready")

# %% [markdown]
# ## A small simulated foam
# Gas bubbles in a 10 mm liquid square, 32 parallel-beam views of 512 pixels.
# The liquid square alone is the stationary background: the server fits
# `data - background`, the projection of the bubbles.

# %%
phantom = foam2d(args.seed, n_bubbles=args.bubbles)
geometry = default_geometry_2d(32, det_count=512, pixel_size=0.03)
scan = simulate_2d(phantom, geometry, method="mesh", photons=1e5, seed=args.seed)
print(f"{len(phantom.bubbles)} bubbles, projections {scan.data.shape}")

# %% [markdown]
# ## Initial guess: circles near each bubble (9 control points, 2 subdivision levels)

# %%
rng = np.random.default_rng(args.seed)
truth_r = [np.sqrt(b.area / np.pi) for b in phantom.bubbles]
initial = [
    circle_surface(b.centroid + rng.normal(scale=0.1 * r, size=2), 0.9 * r, phantom.contrast, control=9, levels=2)
    for b, r in zip(phantom.bubbles, truth_r)
]

# %% [markdown]
# ## Create the job (geometry, data, background and topology go up once) and fit

# %%
job = client.create_job(geometry, data=scan.data, background=scan.background, surfaces=initial)
print(f"job {job.job_id}: {job.info()['memory_bytes']} bytes on the server")
t0 = time.perf_counter()
result = fit(job, initial, iterations=args.iterations, progress=False)
print(f"fit: {result.iterations} iterations, {result.evaluations} remote evaluations, "
      f"{time.perf_counter() - t0:.1f} s, objective {result.history[0]['objective']:.4g} -> {result.objective:.4g}"
      if result.history else f"fit: objective {result.objective:.4g}")

# %% [markdown]
# ## Result: each fitted bubble against the truth

# %%
print(f"{'bubble':>6} {'true area':>10} {'fit area':>9} {'centre error mm':>16}")
errors = []
for k, (fitted, true) in enumerate(zip(result.surfaces, phantom.bubbles)):
    fine = fitted.fine()
    err = float(np.linalg.norm(fine.centroid - true.centroid))
    errors.append(abs(fine.area / true.area - 1))
    print(f"{k:>6} {true.area:>10.3f} {fine.area:>9.3f} {err:>16.4f}")
print(f"largest relative area error: {100 * max(errors):.1f} %")

# %%
job.delete()
client.close()
if server_process is not None:
    server_process.terminate()
    server_process.wait(30)
