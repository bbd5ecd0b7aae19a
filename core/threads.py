"""Worker threads shared by the projectors: one persistent pool per worker count.

The projectors split each call into a few pieces (projection groups, voxel
slabs) that compiled code runs without the GIL. Starting a fresh pool per
call would make every objective evaluation wait for new threads to start
(under load 2 ms per thread, about 3 s of a 47 s reconstruction). The pools here
live for the process (a forked child starts its own); a piece that itself
asks for threads runs them in its own thread, so nested calls cannot
deadlock the pool.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

__all__ = ["thread_map"]

_PREFIX = "bubsub-worker"
_LOCK = threading.Lock()
_POOLS = {}


def _forget_pools():
    _POOLS.clear()  # the parent's worker threads do not exist in a forked child


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pools)


def _pool(workers):
    with _LOCK:
        pool = _POOLS.get(workers)
        if pool is None:
            pool = _POOLS[workers] = ThreadPoolExecutor(workers, thread_name_prefix=f"{_PREFIX}-{workers}")
        return pool


def thread_map(fn, items, threads):
    """``[fn(i) for i in items]``, on up to ``threads`` worker threads when there is more than one item.

    Parameters
    ----------
    fn : callable
    items : iterable
    threads : int
        Most workers to use at once.

    Returns
    -------
    list
        In the order of ``items``; the first exception raised by ``fn`` propagates.
    """
    items = list(items)
    nested = threading.current_thread().name.startswith(_PREFIX)
    if threads > 1 and len(items) > 1 and not nested:
        return list(_pool(min(int(threads), len(items))).map(fn, items))
    return [fn(i) for i in items]
