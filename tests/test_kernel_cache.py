"""The compiled kernels come from numba's disk cache in a new process: no backend compiles anything twice.

Every numba function of the backends (``raster_kernels``, ``embree_kernels``,
``common_kernels``) and the Embree filter callback (a ``cfunc``) is defined at
module level with ``cache=True`` (``backends/jit.py``), and nothing
process-specific (a ctypes function, a closure's captured values) enters a
compiled function's type, so a second process loads each from the cache.
``python -m bubsub.bench projector --startup 5`` times a fresh process's first projection.
"""

import json
import subprocess
import sys

CODE = """
import json
from numba.core.registry import CPUDispatcher
from bubsub.core import MeshProjector, ScanGeometry, sphere_surface
from bubsub.core.projection.backends import common_kernels, embree_kernels, raster_kernels
g = ScanGeometry.cone([0.0, 1.0], source_origin=20.0, origin_detector=15.0, pixel_size=0.1, cols=16, rows=12)
s = [sphere_surface((0, 0, 0), 0.5, 0.3)]
for backend in ("raster", "native"):
    P = MeshProjector(g, backend=backend)
    P.objective(s, P.forward(s))
stats = {}
for module in (common_kernels, embree_kernels, raster_kernels):
    for name, f in vars(module).items():
        if isinstance(f, CPUDispatcher) and f.signatures:
            stats[f"{module.__name__.rsplit('.', 1)[1]}.{name}"] = (sum(f.stats.cache_hits.values()),
                                                                 sum(f.stats.cache_misses.values()))
stats["embree_kernels.record_and_reject (cfunc)"] = (embree_kernels.record_and_reject.cache_hits, 0)
print(json.dumps(stats))
"""


def test_every_backend_kernel_loads_from_the_disk_cache_in_a_new_process():
    runs = [subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, timeout=300) for _ in range(2)]
    for r in runs:
        assert r.returncode == 0, r.stderr[-2000:]
    second = json.loads(runs[1].stdout.strip().splitlines()[-1])
    # the first process filled the cache (or found it filled); the second compiles nothing
    for must in ("raster_kernels.raster3d", "embree_kernels.kernel", "common_kernels.residual",
                 "embree_kernels.record_and_reject (cfunc)"):
        assert must in second, sorted(second)
    for name, (hits, misses) in second.items():
        assert hits >= 1 and misses == 0, (name, hits, misses)
