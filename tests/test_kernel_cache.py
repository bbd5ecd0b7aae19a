"""The compiled kernels come from numba's disk cache in a new process (no compilation, no new cache files)."""

import subprocess
import sys

CODE = """
import json
from bubsub.core import MeshProjector, ScanGeometry, sphere_surface
from bubsub.core.projection.backends import embree_kernels, raster_kernels
g = ScanGeometry.cone([0.0, 1.0], source_origin=20.0, origin_detector=15.0, pixel_size=0.1, cols=16, rows=12)
s = [sphere_surface((0, 0, 0), 0.5, 0.3)]
for backend in ("raster", "native"):
    P = MeshProjector(g, backend=backend)
    P.objective(s, P.forward(s))
stats = {name: (sum(f.stats.cache_hits.values()), sum(f.stats.cache_misses.values()))
         for name, f in (("raster3d", raster_kernels.raster3d), ("embree kernel", embree_kernels.kernel))}
print(json.dumps(stats))
"""


def test_raster_and_embree_kernels_load_from_the_disk_cache_in_a_new_process():
    import json

    runs = [subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, timeout=300) for _ in range(2)]
    for r in runs:
        assert r.returncode == 0, r.stderr[-2000:]
    second = json.loads(runs[1].stdout.strip().splitlines()[-1])
    for name, (hits, misses) in second.items():
        # the first process filled the cache (or found it filled); the second compiles nothing
        assert hits >= 1 and misses == 0, (name, hits, misses)
