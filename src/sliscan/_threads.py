"""Threads for the compiled per-pixel kernels: how many, and how rows are shared among them.

The kernels (`numba.njit(nogil=True)`) release the GIL, so plain threads run them in parallel
over blocks of image rows; each kernel writes only its own rows of preallocated outputs.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np
from numpy.typing import NDArray

#: Environment variable capping the threads of the parallel stages (set by `sliscan.batch` in
#: each worker process, so that worker processes sharing a machine do not oversubscribe it).
THREADS_ENV = "SLISCAN_THREADS"


def available_cpus() -> int:
    """The CPUs this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def default_workers() -> int:
    """Threads for the parallel stages: ``$SLISCAN_THREADS`` if set (a positive integer), else
    the CPUs this process may run on."""
    cap = os.environ.get(THREADS_ENV, "")
    return int(cap) if cap.isdigit() and int(cap) > 0 else available_cpus()


def over_rows(kernel: Callable[[NDArray[np.intp]], object], height: int, workers: int | None = None) -> None:
    """Run ``kernel(rows)`` on blocks of the row indices ``0 .. height - 1``, in parallel.

    Four blocks per thread balance rows of unequal cost (shadow, background).  With one
    worker the kernel runs once on all rows, in this thread.
    """
    workers = default_workers() if workers is None else workers
    if workers <= 1:
        kernel(np.arange(height))
        return
    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(kernel, np.array_split(np.arange(height), 4 * workers)))
