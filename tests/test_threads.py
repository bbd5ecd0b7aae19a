import os
import signal
import threading

import pytest

from bubsub.core.threads import thread_map


def test_thread_map_keeps_order_reuses_its_workers_and_propagates_errors():
    names = []

    def work(i):
        names.append(threading.current_thread())  # the thread objects: a new pool's would be new ones
        return i * i

    for _ in range(5):
        assert thread_map(work, range(6), 2) == [0, 1, 4, 9, 16, 25]
    # the same (at most) two workers over every call, not new threads per call; the pool starts its
    # second thread lazily, only when a task finds the first one busy, so either may be missing
    assert 1 <= len(set(names)) <= 2 and all(t.name.startswith("bubsub-worker-2_") for t in names)

    def boom(i):
        if i == 3:
            raise ValueError("item 3")
        return i

    with pytest.raises(ValueError, match="item 3"):
        thread_map(boom, range(5), 2)


def test_nested_thread_map_runs_inline_instead_of_deadlocking():
    def outer(i):
        return sum(thread_map(lambda j: i * j, range(4), 2))

    assert thread_map(outer, range(4), 2) == [0, 6, 12, 18]


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_a_forked_child_starts_its_own_workers():
    thread_map(lambda i: i, range(2), 2)  # the parent has a pool
    pid = os.fork()
    if pid == 0:  # child: the parent's worker threads do not exist here
        signal.alarm(20)  # a deadlocked child dies instead of hanging the test
        try:
            ok = thread_map(lambda i: i + 1, range(4), 2) == [1, 2, 3, 4]
        finally:
            os._exit(0 if ok else 1)
    _, status = os.waitpid(pid, 0)
    assert os.WEXITSTATUS(status) == 0
