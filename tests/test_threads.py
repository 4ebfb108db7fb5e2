"""The thread pools of the compiled kernels (`sliscan._threads`)."""

import os
import signal
import threading
import time

import numpy as np

from sliscan._threads import (THREADS_ENV, default_workers, in_parallel, over_rows, pool, results_in_order,
                              side_by_side)


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


def test_results_in_order_come_in_the_tasks_order_while_the_later_ones_run():
    """Results in order although the first task finishes last, computed ahead on the pool."""
    started = []

    def task(k, delay):
        def run():
            started.append(k)
            time.sleep(delay)
            return k, threading.current_thread().name
        return run

    results = results_in_order([task(0, 0.2), task(1, 0.0), task(2, 0.0)], workers=2)
    first = next(results)
    assert first[0] == 0 and sorted(started) == [0, 1, 2]  # the others ran while the first was awaited
    assert [k for k, _ in [first, *results]] == [0, 1, 2]
    assert first[1].startswith("sliscan-worker")


def test_results_in_order_with_one_worker_run_each_task_when_asked_for():
    """One worker: each task in this thread, only when its result is asked for; closing the
    iterator leaves the rest unrun."""
    ran = []
    results = results_in_order([lambda k=k: ran.append(k) or threading.current_thread().name for k in range(3)],
                               workers=1)
    assert next(results) == threading.current_thread().name and ran == [0]
    results.close()
    assert ran == [0]


def test_closing_results_in_order_cancels_the_tasks_not_started():
    gate = threading.Event()
    ran = []

    def task(k):
        def run():
            if k:
                gate.wait(5)
            ran.append(k)
            return k
        return run

    results = results_in_order([task(k) for k in range(20)], workers=2)
    assert next(results) == 0  # every task submitted; two of the rest are running, held by the gate
    results.close()  # the ones queued behind them are dropped
    gate.set()
    for _ in range(2):  # the pool finishes what was running before these
        pool(2).submit(lambda: None).result()
    assert 0 in ran and set(ran) <= {0, 1, 2}  # 1 and 2 may not have started before close() dropped them


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


def test_side_by_side_runs_each_call_in_its_own_thread_with_its_share_of_the_workers(monkeypatch):
    """Two chains at once, each seeing half the workers and feeding pools of its own."""
    monkeypatch.setenv(THREADS_ENV, "4")
    barrier = threading.Barrier(2, timeout=10)  # both chains must be running at the same time

    def chain(k):
        barrier.wait()
        workers = default_workers()
        threads = in_parallel(lambda j: threading.current_thread(), range(8))
        return k, threading.current_thread(), workers, set(threads)

    results = side_by_side([lambda: chain(0), lambda: chain(1)])
    assert [k for k, *_ in results] == [0, 1]
    (_, thread_a, workers_a, pool_a), (_, thread_b, workers_b, pool_b) = results
    assert thread_a is not thread_b and threading.current_thread() not in (thread_a, thread_b)
    assert workers_a == workers_b == 2
    # each chain's stages on 2 threads of a pool of its own
    assert 1 <= len(pool_a) <= 2 and 1 <= len(pool_b) <= 2 and not pool_a & pool_b
    assert thread_a not in pool_a and thread_b not in pool_b
    assert default_workers() == 4  # the shares end with the chains


def test_side_by_side_runs_in_turn_with_one_worker_or_inside_a_pool_task(monkeypatch):
    here = threading.current_thread()
    monkeypatch.setenv(THREADS_ENV, "1")
    assert side_by_side([lambda: threading.current_thread(), lambda: threading.current_thread()]) == [here, here]
    monkeypatch.setenv(THREADS_ENV, "2")
    inner = in_parallel(lambda k: (threading.current_thread(), side_by_side([threading.current_thread] * 2)),
                        range(2))
    assert all(chains == [task, task] for task, chains in inner)
    monkeypatch.setenv(THREADS_ENV, "8")  # a chain's own side_by_side: in turn, in the chain's thread
    outer = side_by_side([lambda: (threading.current_thread(), side_by_side([threading.current_thread] * 2))] * 2)
    assert all(chains == [chain, chain] for chain, chains in outer)


def test_side_by_side_gives_each_call_at_least_one_worker_and_passes_errors_on(monkeypatch):
    monkeypatch.setenv(THREADS_ENV, "2")
    assert side_by_side([default_workers] * 3) == [1, 1, 1]
    monkeypatch.setenv(THREADS_ENV, "5")
    assert sorted(side_by_side([default_workers] * 2)) == [2, 3]

    def fails():
        raise ValueError("in a chain")

    try:
        side_by_side([default_workers, fails])
    except ValueError as error:
        assert str(error) == "in a chain"
    else:
        raise AssertionError("the chain's error was lost")
