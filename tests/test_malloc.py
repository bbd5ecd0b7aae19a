"""The C heap's free pages given back: a large array freed below a live one stops being resident."""

import subprocess
import sys

import pytest

from bubsub.core.malloc import release_free_memory

#: Frees a 24 MB array (glibc then raises its mmap threshold to 24 MB), allocates 16 MB and an 8 MB
#: array above it on the heap (larger than any hole the imports left), frees the 16 MB, optionally
#: releases the free memory, and prints how many MB the process gave back.
SCRIPT = """
import sys, numpy as np, psutil
from bubsub.core.malloc import release_free_memory
p = psutil.Process()
a = np.ones(3 << 20); del a
b = np.ones(2 << 20); c = np.ones(1 << 20)
before = p.memory_info().rss
del b
if sys.argv[1] == "released":
    assert release_free_memory()
print((before - p.memory_info().rss) / 2**20)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_a_freed_array_below_a_live_one_is_given_back_on_release():
    # without the release the 16 MB usually stay resident (not always: where the heap's layout leaves the
    # freed array at its top, glibc trims it itself), with it they never do
    back = float(subprocess.run([sys.executable, "-c", SCRIPT, "released"], check=True, capture_output=True,
                                text=True).stdout)
    assert back > 14

