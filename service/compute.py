"""Bounded compute pool: projections run in threads, off the event loop.

At most ``workers`` calls run at a time (Embree releases the GIL while it
traces, so they really run in parallel); up to ``max_queue`` more wait. A
call beyond that, a call over its token's share of the pool, or one whose
estimated memory does not fit next to the running ones (see
:class:`~bubsub.service.budget.ComputeBudget`) is refused at once with 503
and ``Retry-After``, so a busy server sheds load instead of piling up
requests. A call whose request task is cancelled (the shutdown timeout
expired) answers 503 with ``Retry-After`` too: the client retries it.

The same class, with its own bounds, decodes request bodies off the loop.
"""

from __future__ import annotations

import asyncio
import threading
import time
from concurrent.futures import ThreadPoolExecutor

from bubsub.service.errors import APIError

__all__ = ["ComputePool"]


class ComputePool:
    """Thread pool with a bounded waiting line, per-owner shares and a memory budget.

    Parameters
    ----------
    workers : int
        Calls running at once.
    max_queue : int
        Calls allowed to wait for a worker.
    retry_after : int
        Seconds suggested to refused clients.
    per_owner : int, optional
        Calls one owner (token) may have admitted at once (default: no limit
        beyond the pool's).
    budget : ComputeBudget, optional
        Memory budget that calls with ``nbytes`` reserve while they run.
    name : str
        What the pool does, for messages (``compute``, ``decode``).
    """

    def __init__(self, workers, max_queue, retry_after=1, per_owner=None, budget=None, name="compute"):
        self.workers = int(workers)
        self.max_queue = int(max_queue)
        self.retry_after = int(retry_after)
        self.per_owner = None if per_owner is None else int(per_owner)
        self.budget = budget
        self.name = name
        self._executor = ThreadPoolExecutor(self.workers, thread_name_prefix=f"bubsub-{name}")
        self.pending = 0  # admitted and not finished (running + waiting)
        self.running = 0
        self.rejected_total = 0
        self.cancelled_total = 0
        self.timeouts_total = 0  # computations stopped at their compute timeout (504)
        self.seconds = {}  # op -> total seconds
        self.calls = {}  # op -> count
        self._owners = {}  # owner -> admitted calls
        self._lock = threading.Lock()

    @property
    def queued(self):
        """Calls waiting for a worker."""
        return max(0, self.pending - self.running)

    def _busy(self, detail, code="busy"):
        self.rejected_total += 1
        return APIError(503, f"{detail}; retry after {self.retry_after} s", code,
                        {"Retry-After": str(self.retry_after)})

    def _admit(self, owner, nbytes):
        """Count a call in, or raise 503/507 (called on the event loop)."""
        if self.pending >= self.workers + self.max_queue:
            raise self._busy(f"server busy: {self.running} {self.name} calls running and {self.queued} waiting "
                             f"(limit {self.workers} running + {self.max_queue} waiting)")
        if self.per_owner is not None and self._owners.get(owner, 0) >= self.per_owner:
            raise self._busy(f"this token already has {self._owners[owner]} {self.name} calls admitted, its "
                             f"quota (BUBSUB_TOKEN_MAX_COMPUTATIONS)", "token_busy")
        if nbytes and self.budget is not None:
            try:
                self.budget.reserve(nbytes)
            except APIError as exc:
                self.rejected_total += exc.status == 503
                raise
        with self._lock:
            self.pending += 1
            self._owners[owner] = self._owners.get(owner, 0) + 1

    def _release(self, owner, nbytes):
        """Count a call out (called from the worker thread when it ends, even if its request was cancelled)."""
        with self._lock:
            self.pending -= 1
            left = self._owners.get(owner, 1) - 1
            if left:
                self._owners[owner] = left
            else:
                self._owners.pop(owner, None)
        if nbytes and self.budget is not None:
            self.budget.release(nbytes)

    async def run(self, op, fn, *args, owner=None, nbytes=0):
        """Run ``fn(*args)`` in the pool and return its result.

        Parameters
        ----------
        op : str
            Operation name for the metrics (``forward``, ``vjp``, ...).
        fn : callable
        owner : str, optional
            Owner (token) the call counts against.
        nbytes : int
            Estimated memory of the call, reserved from the budget until it ends.

        Raises
        ------
        APIError
            503 when the pool or the owner's share is full, when the memory
            budget is taken by running calls, or when the request was
            cancelled while waiting; 507 when ``nbytes`` exceeds the whole budget.
        """
        self._admit(owner, nbytes)
        try:
            future = self._executor.submit(self._timed, op, fn, args)
        except RuntimeError:  # the pool is shut down
            self._release(owner, nbytes)
            raise self._busy("server shutting down", "shutting_down") from None
        # the slot is freed when the thread ends, not when the awaiting request goes away
        future.add_done_callback(lambda _f: self._release(owner, nbytes))
        try:
            return await asyncio.wrap_future(future)
        except asyncio.CancelledError:
            # uvicorn cancels requests still running when the shutdown timeout expires:
            # answer 503 + Retry-After (retried by the client), not uvicorn's 500
            future.cancel()
            self.cancelled_total += 1
            task = asyncio.current_task()
            if task is not None and hasattr(task, "uncancel"):
                task.uncancel()  # the cancellation is answered here; later awaits must not see it
            raise APIError(503, f"{op} cancelled: the server is shutting down; retry after "
                                f"{self.retry_after} s", "cancelled", {"Retry-After": str(self.retry_after)}) from None

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
