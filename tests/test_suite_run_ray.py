"""`oodrl suite run --ray` (SPEC §16): each pipeline a Ray task in its own clone; a node killed
mid-task, its task runs again on another node, and the head's checkout ends with the dvc.lock
files of a serial run, byte for byte. A real local Ray cluster (a head and one-CPU nodes)."""

from __future__ import annotations

import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from suite_repo import SUITE, locks

from oodrl.suite.run import _check_reachable, run_suite

pytestmark = pytest.mark.slow


@pytest.fixture
def ray_cluster():
    """A local Ray cluster: a head with no CPUs and two one-CPU nodes."""
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 0})
    workers = [cluster.add_node(num_cpus=1) for _ in range(2)]
    cluster.wait_for_nodes()
    yield cluster, workers
    cluster.shutdown()


def _tasks_past_their_first_stage(since: float) -> list[Path]:
    """Task directories (this test's: newer than `since`) whose pipeline has begun its stages."""
    scratch = Path(tempfile.gettempdir())
    return [task for task in scratch.glob("oodrl-suite-*") if _began(task, since)]


def _began(task: Path, since: float) -> bool:
    try:
        return any(p.stat().st_mtime > since for p in task.glob("repo/**/data/params.checked"))
    except FileNotFoundError:  # a task that just ended took its directory with it
        return False


def test_ray_tasks_survive_a_node_killed_mid_task(fresh_suite, serial_locks, ray_cluster, tmp_path):
    from oodrl.testing.pipeline import run

    cluster, (doomed, survivor) = ray_cluster
    _check_reachable(cluster.address)  # a real Ray head passes the handshake: no error
    (tmp_path / "remote").mkdir()  # oodrl creates no remote (SPEC §22)
    run(fresh_suite, "dvc", "remote", "add", "--local", "-d", "lab", str(tmp_path / "remote"))
    start = time.time()
    lines: list[str] = []
    with ThreadPoolExecutor(max_workers=1) as pool:
        suite = pool.submit(run_suite, fresh_suite, ray_address=cluster.address, echo=lines.append)
        while len(tasks := _tasks_past_their_first_stage(start)) < 2:  # one on each node
            assert not suite.done(), suite.exception()
            time.sleep(0.2)
        cluster.remove_node(doomed, allow_graceful=False)
        replacement = cluster.add_node(num_cpus=1)
        first = suite.result(timeout=1200)  # a guard against a hang: a loaded 2-core machine

    nodes = {built.pipeline: built.node for built in first.pipelines}
    assert sorted(nodes) == [".", "pipeline/cartpole"]
    assert set(nodes.values()) == {survivor.node_id, replacement.node_id}  # not doomed's
    assert locks(fresh_suite) == serial_locks
    assert first.head_ran == (f"{SUITE}:leaderboard",)
    for project in [".", "pipeline/cartpole", SUITE]:  # every output is what its lock says
        assert run(fresh_suite / project, "dvc", "status", "--quiet", check=False).returncode == 0

    again = run_suite(fresh_suite, ray_address=cluster.address, echo=lines.append)
    assert (again.pipelines, again.head_ran) == ((), ())
    # The killed task's folder outlived it on its machine (this one); the next run removed it.
    assert [task for task in tasks if task.exists()] == []
    assert locks(fresh_suite) == serial_locks
