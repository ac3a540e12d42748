"""Run independent jobs in forked worker processes, or serially: results in job order.

Results never depend on the worker count: each job is a pure function of its arguments (its
own seed included), and the results come back in the order of the jobs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

#: Pinned to one thread in every stage process (`oodrl.cli`) and suite task (`oodrl.suite.run`).
#: Stages parallelise explicitly (executor.workers processes); library thread pools would
#: oversubscribe the cores (OpenMP threads spin-wait: 10x slowdowns seen on 2 cores) and let
#: float results depend on the machine's core count.
THREAD_POOL_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def ordered_map(
    function: Callable[..., Any],
    jobs: Sequence[tuple],
    workers: int,
    on_done: Callable[[tuple], None] | None = None,
) -> list:
    """`function(*job)` for every job, in order; `on_done(job)` after each (progress bars).

    Forked processes (`workers` > 1 and more than one job) inherit the parent's imports and
    arguments without pickling them on the way in.
    """
    workers = min(workers, len(jobs))
    results = []
    if workers > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        context = multiprocessing.get_context("fork")
        with ProcessPoolExecutor(workers, mp_context=context) as pool:
            futures = [pool.submit(function, *job) for job in jobs]
            for job, future in zip(jobs, futures, strict=True):
                results.append(future.result())
                if on_done:
                    on_done(job)
        return results
    for job in jobs:
        results.append(function(*job))
        if on_done:
            on_done(job)
    return results
