"""ordered_map: the same results, in job order, whatever the worker count."""

from __future__ import annotations

import os

from oodrl.parallel import ordered_map


def _job(index: int, seed: int) -> tuple[int, int, int]:
    return index, seed * 7 % 11, os.getpid()


def test_results_and_progress_in_job_order_for_any_worker_count():
    jobs = [(i, 100 + i) for i in range(6)]
    runs = {}
    for workers in (1, 2):
        done = []
        results = ordered_map(_job, jobs, workers, on_done=done.append)
        assert done == jobs
        runs[workers] = results
    assert (
        [r[:2] for r in runs[1]]
        == [r[:2] for r in runs[2]]
        == [(i, (100 + i) * 7 % 11) for i in range(6)]
    )
    assert {r[2] for r in runs[1]} == {os.getpid()}
    assert os.getpid() not in {r[2] for r in runs[2]}  # the jobs ran in worker processes
