"""The thread pools of the compiled kernels (`sliscan._threads`)."""

import os
import signal
import threading

import numpy as np

from sliscan._threads import THREADS_ENV, in_parallel, over_rows, pool


def test_in_parallel_keeps_the_order_and_uses_one_kept_pool():
    """Results come in the items' order, from the pool's threads, and the pool is started once."""
    names = in_parallel(lambda k: (k, threading.current_thread().name), range(20), workers=2)
    assert [k for k, _ in names] == list(range(20))
    assert all(name.startswith("sliscan-worker") for _, name in names)
    assert pool(2) is pool(2)
    assert in_parallel(lambda k: threading.current_thread().name, [0], workers=1) == [threading.current_thread().name]


def test_a_task_that_runs_in_parallel_itself_runs_its_items_in_its_own_thread():
    """A pool's task waiting on the same pool could wait forever: nested calls run in turn."""
    outer = in_parallel(lambda k: in_parallel(lambda j: (j, threading.current_thread().name), range(3), workers=2),
                        range(4), workers=2)
    for inner in outer:
        assert [j for j, _ in inner] == [0, 1, 2] and len({name for _, name in inner}) == 1


def test_over_rows_visits_every_row_once(monkeypatch):
    for workers in ("1", "2", "3"):
        monkeypatch.setenv(THREADS_ENV, workers)
        seen = np.zeros(37, int)

        def kernel(rows):
            seen[rows] += 1

        over_rows(kernel, 37)
        assert (seen == 1).all()


def test_a_forked_child_starts_its_own_pool():
    """The parent's pool threads do not exist in a forked child, so the child must not reuse the
    pool object (its tasks would never run)."""
    assert in_parallel(abs, [-1, -2], workers=2) == [1, 2]  # the parent's pool exists
    read, write = os.pipe()
    child = os.fork()
    if child == 0:  # pragma: no cover (the child)
        signal.alarm(20)  # a hung child ends, and the test fails, instead of waiting forever
        try:
            os.write(write, bytes(in_parallel(abs, [-3, -4], workers=2)))
        finally:
            os._exit(0)
    os.close(write)
    _, status = os.waitpid(child, 0)
    assert status == 0 and os.read(read, 2) == bytes([3, 4])
