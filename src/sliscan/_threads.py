"""Threads for the compiled per-pixel kernels: how many, and how rows are shared among them.

The kernels (`numba.njit(nogil=True)`) release the GIL, so plain threads run them in parallel
over blocks of image rows; each kernel writes only its own rows of preallocated outputs.  The
threads are started once per worker count and kept (`pool`): starting two threads costs
0.1-1 ms, as much as a small kernel, and a real-time scan runs a dozen of them per frame.

Two independent chains of stages (a scan's two decodings) run faster side by side, each with
its share of the workers (`side_by_side`), than one after the other with all of them: the
numpy steps between the kernels run on one core, and the other chain's work fills the rest.
Other work that zlib or numpy does without the GIL (deflating an npz file's chunks) streams
its results in order while the later ones run (`results_in_order`).
"""

from __future__ import annotations

import collections
import functools
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, Iterator, Sequence, TypeVar

import numpy as np
from numpy.typing import NDArray

#: Environment variable capping the threads of the parallel stages (set by `sliscan.batch` in
#: each worker process, so that worker processes sharing a machine do not oversubscribe it).
THREADS_ENV = "SLISCAN_THREADS"

_PREFIX = "sliscan-worker"

T = TypeVar("T")
R = TypeVar("R")


def available_cpus() -> int:
    """The CPUs this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


#: This thread's share of the workers and its own pools' group, inside `side_by_side`.
_share = threading.local()


def default_workers() -> int:
    """Threads for the parallel stages: inside `side_by_side`, this chain's share; else
    ``$SLISCAN_THREADS`` if set (a positive integer), else the CPUs this process may run on."""
    share = getattr(_share, "workers", 0)
    if share:
        return share
    cap = os.environ.get(THREADS_ENV, "")
    return int(cap) if cap.isdigit() and int(cap) > 0 else available_cpus()


@functools.lru_cache(maxsize=None)
def pool(workers: int, group: int = 0) -> ThreadPoolExecutor:
    """The process's pool of `workers` threads for `group` (0, or a `side_by_side` chain's),
    started on first use and kept."""
    return ThreadPoolExecutor(workers, thread_name_prefix=_PREFIX)


if hasattr(os, "register_at_fork"):  # a forked child has the pools but not their threads
    os.register_at_fork(after_in_child=lambda: (pool.cache_clear(), _chains.cache_clear()))


def in_parallel(fn: Callable[[T], R], items: Iterable[T], workers: int | None = None) -> list[R]:
    """``[fn(item) for item in items]``, the calls shared among `workers` threads of `pool`
    (default `default_workers`); in this thread when there is one worker or when this thread
    is itself one of a pool's (a task waiting on its own pool could wait forever)."""
    workers = default_workers() if workers is None else workers
    if workers <= 1 or _in_pool_task():
        return [fn(item) for item in items]
    return list(pool(workers, getattr(_share, "group", 0)).map(fn, items))


def results_in_order(tasks: Sequence[Callable[[], R]], workers: int | None = None) -> Iterator[R]:
    """The results of `tasks` in order, computed ahead on `workers` threads of `pool` (default
    `default_workers`), so that the caller can use each (write it out) while the later ones run.

    Every task is submitted at once and its result kept until it is yielded.  With one worker,
    or from inside a pool's task (as `in_parallel`), each task runs in this thread when its
    result is asked for.  Closing the iterator cancels the tasks not started.
    """
    workers = default_workers() if workers is None else workers
    if workers <= 1 or _in_pool_task():
        yield from (task() for task in tasks)
        return
    executor = pool(workers, getattr(_share, "group", 0))
    futures = collections.deque(executor.submit(task) for task in tasks)
    try:
        while futures:
            yield futures.popleft().result()
    finally:
        for future in futures:
            future.cancel()


def _in_pool_task() -> bool:
    """Whether this thread is one of a pool's (a task waiting on its own pool could wait forever)."""
    return threading.current_thread().name.startswith(_PREFIX)


def over_rows(kernel: Callable[[NDArray[np.intp]], object], height: int, workers: int | None = None) -> None:
    """Run ``kernel(rows)`` on blocks of the row indices ``0 .. height - 1``, in parallel.

    Four blocks per thread balance rows of unequal cost (shadow, background).  With one
    worker the kernel runs once on all rows, in this thread.
    """
    workers = default_workers() if workers is None else workers
    if workers <= 1:
        kernel(np.arange(height))
        return
    in_parallel(kernel, np.array_split(np.arange(height), 4 * workers), workers)


def side_by_side(calls: Sequence[Callable[[], R]]) -> list[R]:
    """``[call() for call in calls]``, the calls at once, each in its own thread with its own
    share of `default_workers` (and its own pools) for the parallel stages it runs; in turn, in
    this thread, with one worker or from inside a pool's task or another chain (whose threads
    a nested call could wait on forever).

    On 2 cores a scan's two decodings (`sliscan.pipeline.Scanner`) take 1.1-1.2 s side by side
    at 5 MP against 1.6 s in turn with both cores each (docs/speed.md): between the kernels
    each runs numpy steps on one core.
    """
    workers = default_workers()
    nested = _in_pool_task() or getattr(_share, "workers", 0)
    if len(calls) <= 1 or workers <= 1 or nested:
        return [call() for call in calls]
    shares = [max(1, workers // len(calls) + (i < workers % len(calls))) for i in range(len(calls))]

    def run(index: int) -> R:
        _share.workers, _share.group = shares[index], index + 1
        try:
            return calls[index]()
        finally:
            del _share.workers, _share.group

    return list(_chains(len(calls)).map(run, range(len(calls))))


@functools.lru_cache(maxsize=None)
def _chains(count: int) -> ThreadPoolExecutor:
    """The threads `side_by_side` runs `count` chains in (not pool workers: their stages use
    pools of their own), started on first use and kept."""
    return ThreadPoolExecutor(count, thread_name_prefix="sliscan-chain")
