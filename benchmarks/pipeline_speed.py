"""Where the default benchmark's time goes, in one run.

    python benchmarks/pipeline_speed.py [--params params.yaml] [--workers 0]

1. The simulation floor: roll out every episode the protocol simulates (ID, clean evaluation,
   online headline and online sweep sets) with the batched collector and nothing else.
2. A full `dvc repro` in a fresh copy of the repository, with each stage's wall time.
3. A no-op `dvc repro` right after it.
4. The one-knob re-run: change one injector's parameter and `dvc repro` again.
Prints every figure and the ratios full/floor and one-knob/full.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import yaml

from oodrl.testing.pipeline import copy_project, repro

ROOT = Path(__file__).resolve().parents[1]


def simulation_floor(params_path: Path) -> tuple[float, int]:
    """Seconds to roll out the protocol's simulated episodes, and the number of steps."""
    import torch

    torch.set_num_threads(1)
    from oodrl.config import load_params
    from oodrl.envs import ENVIRONMENTS
    from oodrl.envs.collect import collect
    from oodrl.policies.load import load_policy
    from oodrl.protocol import eval_seeds, id_seeds

    params = load_params(params_path)
    adapter = ENVIRONMENTS.get(params.env.id)()
    policy = load_policy(ROOT / "models" / "policy.pt", mode=params.policy.mode)
    online = [n for n in params.benchmark.injectors if params.injector_classes[n].mode == "online"]
    n_sets = 1 + len(online) * (1 + len(params.anomaly.sweep))
    streams = [id_seeds(params)] + [eval_seeds(params)] * n_sets
    workers = params.executor.resolved_workers
    start = time.perf_counter()
    for seeds in streams:
        collect(adapter, policy, seeds, params.env.T, workers=workers)
    steps = sum(len(s) for s in streams) * params.env.T
    return time.perf_counter() - start, steps


def stage_timings(repo: Path) -> dict[str, float]:
    timings = {}
    for path in sorted((repo / ".oodrl" / "timings").glob("*.json")):
        record = json.loads(path.read_text())
        timings[record["stage"]] = record["wall_s"]
    return timings


def timed_repro(repo: Path) -> tuple[float, list[str]]:
    start = time.perf_counter()
    ran = repro(repo)
    return time.perf_counter() - start, ran


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", type=Path, default=ROOT / "params.yaml")
    args = parser.parse_args()
    params = yaml.safe_load(args.params.read_text())

    floor, steps = simulation_floor(args.params)
    print(f"simulation floor: {steps} steps in {floor:.1f} s ({steps / floor:.0f} steps/s)")

    with tempfile.TemporaryDirectory(prefix="oodrl-speed-") as scratch:
        repo = copy_project(ROOT, Path(scratch) / "repo", params)
        full, ran = timed_repro(repo)
        timings = stage_timings(repo)
        groups: dict[str, list[float]] = defaultdict(list)
        for stage, seconds in timings.items():
            groups[stage.split("@")[0]].append(seconds)
        print(f"full dvc repro: {full:.1f} s, {len(ran)} stages "
              f"(stage bodies {sum(timings.values()):.1f} s; the rest is process start-up "
              "and DVC)")  # fmt: skip
        for group, values in sorted(groups.items(), key=lambda kv: -sum(kv[1])):
            print(f"  {group:14s} {len(values):3d} stages  {sum(values):7.1f} s  "
                  f"(max {max(values):.2f} s)")  # fmt: skip
        noop, _ = timed_repro(repo)
        print(f"no-op dvc repro: {noop:.1f} s")
        injector = "observation_delay"
        edited = yaml.safe_load((repo / "params.yaml").read_text())
        edited["anomaly"]["injectors"][injector]["max_delay"] += 1
        (repo / "params.yaml").write_text(yaml.safe_dump(edited, sort_keys=False))
        knob, ran = timed_repro(repo)
        print(
            f"one-knob re-run (anomaly.injectors.{injector}.max_delay): {knob:.1f} s, "
            f"{len(ran)} stages"
        )
    print(f"ratio full / floor: {full / floor:.1f}x; one-knob / full: {knob / full:.0%}")


if __name__ == "__main__":
    main()
