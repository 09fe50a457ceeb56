"""Simulation threads: GIL-free simulations run side by side, one pool per process.

A Jacobian holds a handful of perturbed vectors on each of a few tests of
unequal length. Spread over the cores test by test (a parallel loop over the
rows of one test), a batch of n rows costs ceil(n/2) simulations on two cores
and a residual evaluation (one row per test) runs on one core. One flat list
of (test, row) jobs, longest first, keeps every core busy. Each job is
computed alone, so the result does not depend on how the jobs were shared.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import numba

T = TypeVar("T")

_pool: ThreadPoolExecutor | None = None
_lock = threading.Lock()


def simulation_threads() -> int:
    """Threads the simulations use (numba's setting: ``NUMBA_NUM_THREADS``, else the cores)."""
    return max(1, int(numba.config.NUMBA_NUM_THREADS))


def _executor() -> ThreadPoolExecutor:
    global _pool
    with _lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=simulation_threads(),
                                       thread_name_prefix="mbst-sim")
        return _pool


def run_longest_first(jobs: Sequence[Callable[[], T]], costs: Sequence[float]) -> list[T]:
    """Run ``jobs`` (callables that release the GIL) on the simulation threads.

    Submitted longest first (``costs``: any measure proportional to run time),
    which keeps the last job from running alone. Results in the order of ``jobs``.
    The jobs must not themselves call this function (no nested pools).
    """
    if len(jobs) <= 1 or simulation_threads() == 1:
        return [job() for job in jobs]
    pool = _executor()
    futures = {i: pool.submit(jobs[i])
               for i in sorted(range(len(jobs)), key=lambda i: -costs[i])}
    return [futures[i].result() for i in range(len(jobs))]
