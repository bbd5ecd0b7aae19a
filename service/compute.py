"""Bounded compute pool: projections run in threads, off the event loop.

At most ``workers`` calls run at a time (Embree releases the GIL while it
traces, so they really run in parallel); up to ``max_queue`` more wait. A
call beyond that is refused at once with 503 and ``Retry-After``, so a busy
server sheds load instead of piling up requests.
"""

from __future__ import annotations

import asyncio
import threading
import time
from concurrent.futures import ThreadPoolExecutor

from .errors import APIError

__all__ = ["ComputePool"]


class ComputePool:
    """Thread pool with a bounded waiting line.

    Parameters
    ----------
    workers : int
        Calls running at once.
    max_queue : int
        Calls allowed to wait for a worker.
    retry_after : int
        Seconds suggested to refused clients.
    """

    def __init__(self, workers, max_queue, retry_after=1):
        self.workers = int(workers)
        self.max_queue = int(max_queue)
        self.retry_after = int(retry_after)
        self._executor = ThreadPoolExecutor(self.workers, thread_name_prefix="bubsub-compute")
        self.pending = 0  # admitted and not finished (running + waiting)
        self.running = 0
        self.rejected_total = 0
        self.seconds = {}  # op -> total seconds
        self.calls = {}  # op -> count
        self._lock = threading.Lock()

    @property
    def queued(self):
        """Calls waiting for a worker."""
        return max(0, self.pending - self.running)

    async def run(self, op, fn, *args):
        """Run ``fn(*args)`` in the pool and return its result.

        Parameters
        ----------
        op : str
            Operation name for the metrics (``forward``, ``vjp``, ...).
        fn : callable

        Raises
        ------
        APIError
            503 when all workers are busy and the queue is full.
        """
        if self.pending >= self.workers + self.max_queue:
            self.rejected_total += 1
            raise APIError(503, f"server busy: {self.running} projections running and {self.queued} waiting "
                                f"(BUBSUB_WORKERS={self.workers}, BUBSUB_MAX_QUEUE={self.max_queue}); retry "
                                f"after {self.retry_after} s", "busy", {"Retry-After": str(self.retry_after)})
        self.pending += 1
        loop = asyncio.get_running_loop()
        try:
            return await loop.run_in_executor(self._executor, self._timed, op, fn, args)
        finally:
            self.pending -= 1

    def _timed(self, op, fn, args):
        with self._lock:
            self.running += 1
        t0 = time.perf_counter()
        try:
            return fn(*args)
        finally:
            dt = time.perf_counter() - t0
            with self._lock:
                self.running -= 1
                self.seconds[op] = self.seconds.get(op, 0.0) + dt
                self.calls[op] = self.calls.get(op, 0) + 1

    def shutdown(self, wait=True):
        """Finish running calls (``wait``) and stop the threads."""
        self._executor.shutdown(wait=wait, cancel_futures=not wait)
