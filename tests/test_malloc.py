"""glibc's mmap threshold fixed: a large array freed after others is given back to the operating system."""

import subprocess
import sys

import pytest

from bubsub.core.malloc import MMAP_THRESHOLD, environment, release_large_arrays

#: Frees a 24 MB array (glibc then raises its mmap threshold to 24 MB), allocates 16 MB and a 1 MB
#: array above it on the heap, frees the 16 MB, and prints how much of it is still resident (MB).
SCRIPT = """
import sys, numpy as np, psutil
from bubsub.core.malloc import release_large_arrays
if sys.argv[1] == "fixed":
    assert release_large_arrays()
p = psutil.Process()
a = np.ones(3 << 20); del a
before = p.memory_info().rss
b = np.ones(2 << 20); c = np.ones(1 << 17); del b
print((p.memory_info().rss - before) / 2**20)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_a_freed_large_array_is_given_back_once_the_threshold_is_fixed():
    kept = {mode: float(subprocess.run([sys.executable, "-c", SCRIPT, mode], check=True, capture_output=True,
                                       text=True).stdout) for mode in ("dynamic", "fixed")}
    assert kept["dynamic"] > 14  # the 16 MB stayed resident on the heap
    assert kept["fixed"] < 4


def test_the_environment_sets_the_same_threshold():
    assert environment() == {"MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD)}
    assert release_large_arrays() in (True, False)
