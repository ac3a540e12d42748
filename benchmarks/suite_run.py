"""`oodrl suite run` against a serial build of the suite (SPEC §16), in one run.

    python benchmarks/suite_run.py [--pipelines . pipeline/cartpole …] [--params ci/params.yaml]
                                   [--detectors D …] [--injectors I …] [--workers 2]
                                   [--ray-nodes 2] [--json OUT]

Three fresh copies of the project's HEAD with the same params (default: ci/params.yaml, the tiny
CI protocol; `--params params.yaml` for the full one; --detectors/--injectors cut the benchmark):
1. serial: `dvc repro` of each pipeline's DVC project in turn, then the suite's leaderboard;
2. `oodrl suite run --workers N`: local processes, no remote (the clones use the head's cache);
3. the same on a local Ray cluster: a head with no CPUs, N one-CPU nodes, a directory remote.
2 and 3 must leave the serial run's dvc.lock files byte for byte. Then the makespan on 8, 32 and
128 nodes, simulated from the serial per-pipeline times: list scheduling, longest first; the head
restores each project when its pipeline ends, one at a time (the restore times measured in 2),
then runs the leaderboard (the serial run's time); the critical path is the longest pipeline plus
the leaderboard.
Both local runs also report their CPU seconds (every child process's user and system time): the
serial run keeps more than one core busy at times (a stage's worker processes), so no run on N
cores doing the same work beats its CPU seconds / N, whatever the scheduling.
"""

from __future__ import annotations

import argparse
import heapq
import json
import resource
import tempfile
import time
from pathlib import Path

import yaml

from oodrl.config import EXTENDS_KEY, merge_params
from oodrl.suite.run import run_suite
from oodrl.testing.pipeline import run
from oodrl.testing.suite import SUITE, head_commit, locks, serial_build, suite_copy

ROOT = Path(__file__).resolve().parents[1]
SIMULATED_NODES = (8, 32, 128)


def list_schedule(seconds: list[float], nodes: int) -> list[float]:
    """When each job ends (in the order given), each started longest first on the node free
    earliest."""
    free_at = [0.0] * nodes
    ends = [0.0] * len(seconds)
    for job in sorted(range(len(seconds)), key=lambda j: -seconds[j]):
        ends[job] = free_at[0] + seconds[job]
        heapq.heapreplace(free_at, ends[job])
    return ends


def makespan(seconds: list[float], restores: list[float], leaderboard: float, nodes: int) -> float:
    """The head restores each pipeline when it ends, one at a time, then runs the leaderboard."""
    head_free = 0.0
    for end, restore in sorted(zip(list_schedule(seconds, nodes), restores, strict=True)):
        head_free = max(head_free, end) + restore
    return head_free + leaderboard


def children_cpu_s() -> float:
    """User and system seconds of every child process waited for so far (theirs included)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def timed_suite_run(repo: Path, **how) -> tuple[float, object]:
    start = time.perf_counter()
    result = run_suite(repo, echo=lambda line: print(f"  {line}", flush=True), **how)
    return time.perf_counter() - start, result


def on_local_ray_cluster(repo: Path, nodes: int, remote: Path) -> tuple[float, object]:
    from ray.cluster_utils import Cluster

    run(repo, "dvc", "remote", "add", "--local", "-d", "bench", str(remote))
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 0})
    try:
        for _ in range(nodes):
            cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        return timed_suite_run(repo, ray_address=cluster.address)
    finally:
        cluster.shutdown()


def main() -> None:
    from oodrl.suite.pipeline import suite_pipelines

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    every = suite_pipelines(ROOT)
    parser.add_argument(
        "--pipelines", nargs="+", default=every, help="default: the suite; always with the root's"
    )
    parser.add_argument("--params", type=Path, default=ROOT / "ci" / "params.yaml")
    parser.add_argument("--detectors", nargs="+", help="benchmark.detectors (default: params')")
    parser.add_argument("--injectors", nargs="+", help="benchmark.injectors (default: params')")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--ray-nodes", type=int, default=2, help="0: no Ray run")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    args = parser.parse_args()

    overrides = yaml.safe_load(args.params.read_text())
    overrides.pop(EXTENDS_KEY, None)  # merged onto the copied commit's own params.yaml

    def edit(shared: dict) -> None:
        merged = merge_params(shared, overrides)
        shared.clear()
        shared.update(merged)
        for key in ("detectors", "injectors"):
            if getattr(args, key):
                shared["benchmark"][key] = getattr(args, key)

    def save(figures: dict) -> None:
        """After each run, so that an interrupted benchmark keeps what it measured."""
        if args.json:
            args.json.write_text(json.dumps(figures, indent=2, sort_keys=True) + "\n")

    # The root's pipeline is always one of the suite's (suite_pipelines): `oodrl suite run`
    # builds it whatever --pipelines says, so the serial run must build it too.
    pipelines = [".", *(p for p in args.pipelines if p != ".")]
    commit = head_commit(ROOT)
    figures: dict = {"commit": commit, "params": str(args.params), "pipelines": pipelines}
    with tempfile.TemporaryDirectory() as tmp:
        copies = {
            name: suite_copy(ROOT, commit, Path(tmp) / name, pipelines, edit)
            for name in ("serial", "workers", "ray")[: 3 if args.ray_nodes else 2]
        }
        print("serial:", flush=True)
        cpu_before = children_cpu_s()
        serial = serial_build(copies["serial"], pipelines)
        serial_cpu_s = children_cpu_s() - cpu_before
        for project, (seconds, ran) in serial.items():
            print(f"  {project}: {seconds:.1f} s ({len(ran)} stages)", flush=True)
        serial_s = sum(seconds for seconds, _ in serial.values())
        reference = locks(copies["serial"])
        per_pipeline = {p: seconds for p, (seconds, _) in serial.items() if p != SUITE}
        # The bound: the same CPU seconds spread over `workers` cores with no core ever idle.
        bound = serial_cpu_s / (args.workers * serial_s)
        print(f"serial: {serial_s:.1f} s, {serial_cpu_s:.1f} CPU s "
              f"({serial_cpu_s / serial_s:.2f} cores busy on average)", flush=True)  # fmt: skip
        figures.update(serial_s=serial_s, per_pipeline_serial_s=per_pipeline,
                       serial_cpu_s=serial_cpu_s, workers_bound=bound)  # fmt: skip
        save(figures)

        print(f"--workers {args.workers}:", flush=True)
        cpu_before = children_cpu_s()
        workers_s, workers = timed_suite_run(copies["workers"], workers=args.workers)
        workers_cpu_s = children_cpu_s() - cpu_before
        assert locks(copies["workers"]) == reference, "--workers: locks differ from serial"
        restore_s = {t.pipeline: t.restore_seconds for t in workers.pipelines}
        figures.update(
            workers=args.workers,
            workers_s=workers_s,
            workers_cpu_s=workers_cpu_s,
            head_after_tasks_s=workers.head_seconds,  # the last restore(s), the leaderboard
            per_pipeline_task_s={t.pipeline: t.seconds for t in workers.pipelines},
            per_pipeline_restore_s=restore_s,
        )
        times = list(per_pipeline.values())
        leaderboard_s = serial[SUITE][0]
        critical = max(times) + leaderboard_s
        restores = [restore_s[p] for p in per_pipeline]
        simulated = {n: makespan(times, restores, leaderboard_s, n) for n in SIMULATED_NODES}
        figures.update(leaderboard_s=leaderboard_s, critical_path_s=critical,
                       simulated_makespan_s=simulated)  # fmt: skip
        save(figures)
        if args.ray_nodes:
            print(f"Ray, {args.ray_nodes} one-CPU nodes:", flush=True)
            ray_s, ray = on_local_ray_cluster(copies["ray"], args.ray_nodes, Path(tmp) / "remote")
            assert locks(copies["ray"]) == reference, "Ray: locks differ from serial"
            figures.update(ray_nodes=args.ray_nodes, ray_s=ray_s, ray_head_s=ray.head_seconds,
                           ray_nodes_used=len({t.node for t in ray.pipelines}))  # fmt: skip
            save(figures)

    print("\n| run | wall time | × serial | CPU time |\n|---|---:|---:|---:|")
    print(f"| serial: `dvc repro` per project, then the suite's | {serial_s:.1f} s | 1.00 "
          f"| {serial_cpu_s:.1f} s |")  # fmt: skip
    print(f"| `--workers {args.workers}` | {workers_s:.1f} s | {workers_s / serial_s:.2f} "
          f"| {workers_cpu_s:.1f} s |")  # fmt: skip
    print(f"| the serial run's CPU time on {args.workers} cores, none idle (a bound) "
          f"| {bound * serial_s:.1f} s | {bound:.2f} | |")  # fmt: skip
    if args.ray_nodes:
        print(f"| Ray, {args.ray_nodes} one-CPU nodes | {ray_s:.1f} s | {ray_s / serial_s:.2f} | |")
    for n, seconds in simulated.items():
        print(f"| simulated, {n} nodes | {seconds:.1f} s | {seconds / serial_s:.2f} "
              f"({seconds / critical:.2f}× the critical path {critical:.1f} s) | |")  # fmt: skip


if __name__ == "__main__":
    main()
