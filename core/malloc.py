"""Freed memory handed back to the operating system between the phases of long work (glibc's malloc).

glibc serves an allocation of at least its mmap threshold (128 kB at first)
with a mapping of its own, unmapped when freed; but each such free raises
the threshold to the freed size, up to 32 MB. After the first large arrays of
a reconstruction are freed, arrays of up to 32 MB (projections of parts of
the detector, face sums, fine meshes, optimiser histories) come from the
heap instead, whose free space stays resident while anything above it
lives, so the resident memory of a long run creeps up phase after phase.
:func:`release_free_memory` (``malloc_trim``) gives the free pages back; the
pipeline calls it at the end of each phase and fit level, where the arrays
of the phase are gone. (Fixing the threshold instead keeps every large array
in a mapping of its own, but then each of them costs fresh pages, page
faults on every objective of a dense column.)
"""

from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ["release_free_memory"]

_libc = []


def _trim():
    if not _libc:
        try:
            trim = ctypes.CDLL(ctypes.util.find_library("c") or None).malloc_trim
            trim.argtypes, trim.restype = (ctypes.c_size_t,), ctypes.c_int
        except (OSError, AttributeError):  # not glibc
            trim = None
        _libc.append(trim)
    return _libc[0]


def release_free_memory():
    """Give the C heap's free pages back to the operating system (see the module docstring).

    Returns
    -------
    bool
        False where the C library has no ``malloc_trim`` (not glibc); True otherwise.
    """
    trim = _trim()
    if trim is None:
        return False
    trim(0)
    return True
