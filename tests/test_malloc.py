"""The C heap's free pages given back: a large array freed below a live one stops being resident."""

import subprocess
import sys

import pytest

from bubsub.core.malloc import release_free_memory

#: Frees a 24 MB array (glibc then raises its mmap threshold to 24 MB), allocates 16 MB and a 1 MB
#: array above it on the heap, frees the 16 MB, optionally releases the free memory, and prints how
#: much of the 16 MB is still resident (MB).
SCRIPT = """
import sys, numpy as np, psutil
from bubsub.core.malloc import release_free_memory
p = psutil.Process()
a = np.ones(3 << 20); del a
before = p.memory_info().rss
b = np.ones(2 << 20); c = np.ones(1 << 17); del b
if sys.argv[1] == "released":
    assert release_free_memory()
print((p.memory_info().rss - before) / 2**20)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_a_freed_array_below_a_live_one_is_given_back_on_release():
    kept = {mode: float(subprocess.run([sys.executable, "-c", SCRIPT, mode], check=True, capture_output=True,
                                       text=True).stdout) for mode in ("kept", "released")}
    assert kept["kept"] > 14  # the 16 MB stayed resident on the heap
    assert kept["released"] < 4

