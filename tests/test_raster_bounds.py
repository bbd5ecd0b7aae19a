"""The raster backend's kernels index arrays without bounds checks (numba's default): one write past
an array's end corrupts the heap silently and crashes a later, unrelated test. This runs every
kernel path once in a subprocess compiled with ``NUMBA_BOUNDSCHECK=1``, where such an access
raises IndexError instead."""

import os
import sys

import pytest
from kernel_paths import RASTER_PATHS


def bounds_checked_run(tmp):
    env = dict(os.environ, NUMBA_BOUNDSCHECK="1", NUMBA_CACHE_DIR=str(tmp), BUBSUB_RASTER_STORE_MB="")
    return [sys.executable, "-c", "import os\n" + RASTER_PATHS], env, None


@pytest.mark.background(command=bounds_checked_run)  # a compile of every kernel with bounds checks, beside the other tests
def test_raster_kernels_stay_in_bounds(background):
    res = background.wait(600)
    assert res.returncode == 0 and "bounds ok" in res.stdout, res.stdout[-2000:] + res.stderr[-4000:]
