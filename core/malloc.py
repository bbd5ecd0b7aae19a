"""Large arrays handed back to the operating system when freed (glibc's malloc).

glibc serves an allocation of at least its mmap threshold (128 kB at first)
with a mapping of its own, unmapped when freed; but each such free raises
the threshold to the freed size, up to 32 MB. After the first large arrays of
a reconstruction are freed, arrays of tens of megabytes (projections,
residuals, crossing stores, optimiser histories) come from the heap instead,
whose free space is not returned while anything above it lives, so the
resident memory of a long run creeps up phase after phase. Fixing the
threshold keeps every large array in a mapping of its own. On the
~600-bubble column of ``bubsub bench scale`` the peak RSS of
``bubsub reconstruct`` went from 1026 MiB to 914 MiB.
"""

from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ["MMAP_THRESHOLD", "release_large_arrays", "environment"]

#: Bytes from which an allocation gets a mapping of its own.
MMAP_THRESHOLD = 1 << 20

_M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter numbers (malloc.h)


def release_large_arrays():
    """Fix glibc's mmap threshold at :data:`MMAP_THRESHOLD` in this process (see the module docstring).

    Returns
    -------
    bool
        Whether it was set: False where the C library has no ``mallopt`` (not glibc).
    """
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1


def environment():
    """Environment variables that set the same threshold in a process started with them (Dask workers)."""
    return {"MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD)}
