"""The suite's pipelines against their simulation floor, in one run (SPEC §12).

    python benchmarks/pipeline_speed.py [--pipelines . pipeline/cartpole …] [--no-knobs]
                                        [--cache-dir DIR] [--json OUT] [--baseline REV]

In a fresh copy of the repository (committed policies, no outputs):
1. Per pipeline, its two simulation floors:
   - the project floor: roll out every episode it simulates (ID, clean evaluation and
     held-out calibration, audit and twin sets, each online injector's headline and sweep sets,
     the impact curves with their tier searches and verifications, and
     the tier sets) with the collector and nothing else — no stores written, no detectors;
   - the physical floor: as many raw `env.step` calls as the project floor simulated
     stream-steps (impact episodes included), with no policy, no fault, no I/O: random valid
     actions drawn from the action space beforehand, a reset at each episode's end, split over
     the same number of worker processes. Random actions end some episodes sooner than the
     policy does (LunarLander crashes), so it pays for more resets than the project floor.
2. Per pipeline, a full `dvc repro` in its directory (each pipeline is a DVC project of its
   own), the seconds spent inside its stage commands (the rest is process start-up and DVC's
   own bookkeeping) and whether it reproduced the committed locks byte for byte; then the
   suite's leaderboard (only when every pipeline is built).
3. A no-op `dvc repro` of every project built (one after another), `dvc status` of the root, and
   the seconds DVC takes to build the root's index (every dvc.yaml and dvc.lock of the project
   parsed into stages): every DVC command builds it, and `dvc exp run` builds it again after
   each stage it runs.
4. On the root pipeline (LunarLander, the paper default): one injector's knob, one detector's
   knob, `dvc exp run -S anomaly.severity=0.6`, and the same variant as an edit of params.yaml,
   `dvc repro` and `dvc exp save`, each timed with the stages it ran.
Prints every figure and the ratios: full / each floor per pipeline (and the project floor / the
physical one), suite / suite floors, each knob / the root's full run. `--cache-dir` shares a DVC
cache (e.g. the checkout's own, so that its `dvc repro` afterwards restores these results from
the run cache instead of recomputing them).
`--baseline REV` first measures 2-4 on a clone of commit REV whose stages run REV's own
sources, so a change is reported before and after in one run, against the same floors (the
floors are the simulation's, computed once with this checkout's code).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# The floor simulates as the collect stages do: their `oodrl` command pins every library thread
# pool to one thread (oodrl.cli) before numpy loads; unpinned, each of the collector's worker
# processes spins up a BLAS pool of its own and the floor is slower than the stages.
for _variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")


from oodrl.testing.pipeline import copy_project, edit_params, repro, run  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SUITE = "pipeline/suite"


@dataclass
class Floor:
    """A pipeline's simulation floors: seconds of the project's collection of every episode it
    simulates, its sets' stream-steps, every stream-step it simulated (impact episodes too) per
    environment adapter, and seconds of as many raw `env.step` calls (0 until measured)."""

    project_s: float
    steps: int
    simulated: dict[tuple, tuple[Any, int]]
    workers: int
    physical_s: float = 0.0

    @property
    def simulated_steps(self) -> int:
        return sum(steps for _, steps in self.simulated.values())


class _StepCount:
    """Counts, while active, the stream-steps the collector simulates per environment adapter.

    Every collection runs its jobs through `oodrl.envs.collect`'s `ordered_map`, each job's
    arguments being (adapter, policy, job of streams, T, policy seed): counted in this process
    before the jobs go to the workers.
    """

    def __init__(self) -> None:
        self.simulated: dict[tuple, tuple[Any, int]] = {}

    def __enter__(self) -> _StepCount:
        from oodrl.envs import collect

        self._original = original = collect.ordered_map

        def counted(function, jobs, workers, on_done=None):
            for adapter, _, job, horizon, _ in jobs:
                key = (adapter.env_id, tuple(sorted(adapter.env_kwargs.items())))
                steps = self.simulated.get(key, (adapter, 0))[1]
                self.simulated[key] = (adapter, steps + len(job.seeds) * horizon)
            return original(function, jobs, workers, on_done)

        collect.ordered_map = counted
        return self

    def __exit__(self, *exc: object) -> None:
        from oodrl.envs import collect

        collect.ordered_map = self._original


def simulation_floor(pipeline: Path) -> Floor:
    """Seconds to simulate every episode a pipeline simulates, as its stages do, and the steps
    of its streams: the ID, clean evaluation and calibration sets, each online injector's
    headline and sweep sets, the impact curves (SPEC §15: the clean and random-policy returns
    once, each fault over its grid; their whole episodes are timed and counted in the simulated
    steps, not in the sets' steps) and each fault's tier sets."""
    from oodrl.config import load_params
    from oodrl.envs import ENVIRONMENTS
    from oodrl.io import yamlio
    from oodrl.io.store import write_trajectories
    from oodrl.policies.load import load_policy
    from oodrl.protocol import streams
    from oodrl.protocol.impact import live_injectors
    from oodrl.protocol.tier_search import calibrate_impact
    from oodrl.protocol.tiers import read_tiers, tier_sets

    params = load_params(pipeline / "params.yaml")
    policy = pipeline / "models" / "policy.pt"
    faults = list(params.benchmark.injectors)
    online = [n for n in faults if params.injector_classes[n].mode == "online"]
    timer, count = _Timer(), _StepCount()
    with timer, count:
        sets = [streams.id_set(params, policy), streams.eval_set(params, policy)]
        sets += [streams.heldout_set(params, which, policy) for which in streams.HELDOUT_SETS]
    with tempfile.TemporaryDirectory() as tmp:
        id_path, eval_path = Path(tmp) / "id.zarr", Path(tmp) / "eval.zarr"
        write_trajectories(id_path, sets[0])  # live faults' reference statistics; not timed
        write_trajectories(eval_path, sets[1])  # post-hoc injectors read it; not timed
        with timer, count:
            for name in online:
                severities = [params.injector_severity(name), *params.anomaly.sweep]
                sets += streams.perturbed_sets(params, name, severities, policy, eval_path)
            document = calibrate_impact(
                ENVIRONMENTS.get(params.env.id)(),
                load_policy(policy, mode=params.policy.mode),
                live_injectors(params, faults, id_path),
                params.tiers.grid,
                params.tiers.episodes,
                search=params.tiers.search,
                seed=params.seed,
                n_boot=params.metrics.n_boot,
                ci=params.metrics.ci,
                workers=params.executor.resolved_workers,
            )
        impact_file = Path(tmp) / "impact.yaml"
        impact_file.write_text(yamlio.dump(document))  # what collect_tiers reads; not timed
        with timer, count:
            for name in faults:
                tiers, _ = read_tiers(impact_file, name)
                if tiers:
                    sets += tier_sets(params, name, tiers, policy, id_path)
    steps = sum(s.states.shape[0] * s.states.shape[1] for s in sets)
    return Floor(timer.seconds, steps, count.simulated, params.executor.resolved_workers)


def physical_floor(floor: Floor) -> float:
    """Seconds of raw `env.step`: as many calls per environment adapter as `floor` simulated
    stream-steps, split over its number of worker processes (wall time, as the project floor)."""
    from oodrl.parallel import ordered_map

    seconds = 0.0
    for adapter, steps in floor.simulated.values():
        shares = [
            steps // floor.workers + (k < steps % floor.workers) for k in range(floor.workers)
        ]
        jobs = [(adapter, share, k) for k, share in enumerate(shares) if share]
        start = time.perf_counter()
        ordered_map(_raw_steps, jobs, floor.workers)
        seconds += time.perf_counter() - start
    return seconds


#: Random actions drawn before stepping, and cycled through.
_ACTION_POOL = 4096


def _raw_steps(adapter, steps: int, seed: int) -> None:
    """`steps` calls of one environment's `env.step` on random valid actions, resets at the ends
    of episodes: the simulator and gymnasium's wrappers, nothing of oodrl."""
    env = adapter.make()
    env.reset(seed=seed)
    env.action_space.seed(seed)
    actions = [env.action_space.sample() for _ in range(min(steps, _ACTION_POOL))]
    step, reset = env.step, env.reset
    for t in range(steps):
        _, _, terminated, truncated, _ = step(actions[t % len(actions)])
        if terminated or truncated:
            reset()
    env.close()


class _Timer:
    """Sums the seconds spent inside its `with` blocks."""

    seconds = 0.0

    def __enter__(self) -> None:
        self._start = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        self.seconds += time.perf_counter() - self._start


def stage_bodies(pipeline: Path) -> float:
    """Seconds inside the stage commands of a pipeline's last run (their own timing records)."""
    records = (pipeline / ".oodrl" / "timings").glob("*.json")
    return sum(json.loads(path.read_text())["wall_s"] for path in records)


def timed_repro(project: Path, *args: str, env: dict | None = None) -> tuple[float, list[str]]:
    """`dvc repro` in one DVC project (the root, or a pipeline's directory)."""
    start = time.perf_counter()
    ran = repro(project, *args, env=env)
    return time.perf_counter() - start, ran


def changed_locks(repo: Path, project: str) -> list[str]:
    """The lock files of `project` that its from-scratch run left different from the committed
    ones ([]: every committed lock reproduced byte for byte)."""
    out = run(repo, "git", "status", "--porcelain", "--", project).stdout
    paths = [line[3:] for line in out.splitlines() if line.endswith("dvc.lock")]
    return [p for p in paths if project != "." or not p.startswith("pipeline/")]


def timed_status(project: Path, env: dict | None = None) -> tuple[float, bool]:
    """`dvc status` of one project: seconds, and whether it printed nothing to do."""
    start = time.perf_counter()
    done = run(project, "dvc", "status", "-q", check=False, env=env)
    return time.perf_counter() - start, done.returncode == 0


def dvc_index(repo: Path) -> tuple[float, int, int]:
    """Seconds to build DVC's index of the repository (best of 3), its stages and DVC files."""
    from dvc.repo import Repo

    best = float("inf")
    with Repo(str(repo)) as dvc:
        for _ in range(3):
            dvc._reset()  # drops the cached index, as DVC does after running a stage command
            start = time.perf_counter()
            index = dvc.index
            best = min(best, time.perf_counter() - start)
        files = {stage.dvcfile.relpath for stage in index.stages}
        return best, len(index.stages), len(files)


def knob_runs(repo: Path, env: dict | None = None) -> dict[str, tuple[float, int]]:
    """Seconds and stages run for each of the design's variants, on the root pipeline."""
    figures = {}

    def injector(p):
        p["anomaly"]["injectors"]["observation_delay"]["max_delay"] = 5

    def detector(p):
        p["detectors"]["kde_density"]["threshold_percentile"] = 98.0

    def severity(p):
        p["anomaly"]["severity"] = 0.6

    for name, edit in [("injector knob", injector), ("detector knob", detector)]:
        edit_params(repo, edit)
        seconds, ran = timed_repro(repo, env=env)
        figures[name] = (seconds, len(ran))
    run(repo, "git", "add", "-A")
    run(repo, "git", "commit", "-q", "-m", "knobs")
    start = time.perf_counter()
    done = run(repo, "dvc", "exp", "run", "-S", "anomaly.severity=0.6", env=env)
    ran = [line for line in done.stdout.splitlines() if line.startswith("Running stage '")]
    figures["dvc exp run -S anomaly.severity=0.6"] = (time.perf_counter() - start, len(ran))
    # The same variant by hand: edit, `dvc repro`, `dvc exp save`. Back at the commit first
    # (untimed); no run cache, which the experiment above has just filled for this variant.
    run(repo, "git", "checkout", "-q", "--", ".")
    run(repo, "dvc", "checkout", "-q")
    edit_params(repo, severity)
    seconds, ran = timed_repro(repo, "--no-run-cache", env=env)
    figures["headline severity, plain dvc repro"] = (seconds, len(ran))
    start = time.perf_counter()
    run(repo, "dvc", "exp", "save", "-n", "severity-0.6", env=env)
    figures["then dvc exp save"] = (time.perf_counter() - start, 0)
    return figures


def main() -> None:
    from oodrl.suite.pipeline import suite_pipelines

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    every = suite_pipelines(ROOT)
    parser.add_argument("--pipelines", nargs="+", default=every, help="default: the suite")
    parser.add_argument("--no-knobs", action="store_true", help="skip the knob re-runs")
    parser.add_argument(
        "--floors-only", action="store_true", help="only the simulation floors (no DVC runs)"
    )
    parser.add_argument("--cache-dir", type=Path, help="the DVC cache the copy uses")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    parser.add_argument("--baseline", metavar="REV", help="also measure commit REV, first")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        repo = copy_project(ROOT, Path(tmp) / "repo")
        floors = {}
        for name in args.pipelines:
            floor = floors[name] = simulation_floor(repo / name)
            floor.physical_s = physical_floor(floor)
            print(f"{name}: {floor.steps} steps in its sets, {floor.simulated_steps} simulated "
                  f"(impact included); project floor {floor.project_s:.1f} s, physical floor "
                  f"{floor.physical_s:.1f} s (raw env.step, {floor.workers} workers): project / "
                  f"physical = {floor.project_s / floor.physical_s:.2f}×", flush=True)  # fmt: skip
        figures = {
            "suite_floor_s": sum(f.project_s for f in floors.values()),
            "suite_physical_floor_s": sum(f.physical_s for f in floors.values()),
        }
        print(f"suite: project floor {figures['suite_floor_s']:.1f} s, physical floor "
              f"{figures['suite_physical_floor_s']:.1f} s", flush=True)  # fmt: skip
        if args.floors_only:
            rows = [{"pipeline": n, **_floor_figures(f)} for n, f in floors.items()]
            write_figures(args.json, {**figures, "pipelines": rows})
            return
        if args.baseline:
            base = Path(tmp) / "baseline"
            run(Path(tmp), "git", "clone", "-q", "--no-checkout", str(ROOT), str(base))
            run(base, "git", "checkout", "-q", args.baseline)
            # The baseline's stage commands import its own sources, not this checkout's.
            path = [str(base / "src"), os.environ.get("PYTHONPATH")]
            env = {"PYTHONPATH": os.pathsep.join(filter(None, path))}
            print(f"-- baseline {args.baseline}", flush=True)
            figures["baseline"] = {"rev": args.baseline, **measure(base, args, floors, every, env)}
            print("-- this checkout", flush=True)
        figures.update(measure(repo, args, floors, every, None))
        write_figures(args.json, figures)


def measure(repo: Path, args, floors: dict, every: list[str], env: dict | None) -> dict:
    """Steps 2-4 on one copy; `env` added to its commands' environment."""
    if args.cache_dir:  # every project's: each names the root's cache in its .dvc/config
        for project in [".", *every[1:], SUITE]:
            run(repo / project, "dvc", "cache", "dir", "--local", str(args.cache_dir.resolve()))
    rows, floor_total, physical_total, full_total = [], 0.0, 0.0, 0.0
    for name in args.pipelines:
        floor = floors[name]
        full, ran = timed_repro(repo / name, env=env)
        bodies = stage_bodies(repo / name)
        changed = changed_locks(repo, name)
        locks = f"CHANGED: {changed}" if changed else "reproduced"
        rows.append({"pipeline": name, **_floor_figures(floor), "full_s": full,
                     "stage_bodies_s": bodies, "stages": len(ran),
                     "locks_changed": changed})  # fmt: skip
        floor_total += floor.project_s
        physical_total += floor.physical_s
        full_total += full
        print(f"{name}: full {full:.1f} s ({len(ran)} stages; {bodies:.1f} s inside stage "
              f"commands) = {full / floor.project_s:.1f}× the project floor, "
              f"{full / floor.physical_s:.1f}× the physical floor; locks {locks}",
              flush=True)  # fmt: skip
    projects = list(args.pipelines)
    if args.pipelines == every:
        seconds, ran = timed_repro(repo / SUITE, env=env)
        full_total += seconds
        projects.append(SUITE)
        print(f"leaderboard: {seconds:.1f} s ({len(ran)} stages)")
    noop = 0.0
    for project in projects:
        seconds, ran = timed_repro(repo / project, env=env)
        assert ran == [], f"the no-op repro of {project} ran {ran}"
        noop += seconds
    status_s, clean = timed_status(repo, env=env)
    index_s, stages, files = dvc_index(repo)
    print(f"suite: project floor {floor_total:.1f} s, physical floor {physical_total:.1f} s; "
          f"full {full_total:.1f} s = {full_total / floor_total:.1f}× the project floor, "
          f"{full_total / physical_total:.1f}× the physical floor; no-op repro of {len(projects)} "
          f"projects {noop:.2f} s; root `dvc status` {status_s:.2f} s "
          f"({'clean' if clean else 'NOT clean'}); DVC's index of the root project "
          f"({stages} stages in {files} DVC files) {index_s:.2f} s", flush=True)  # fmt: skip
    figures = {"pipelines": rows, "suite_floor_s": floor_total,
               "suite_physical_floor_s": physical_total, "suite_full_s": full_total,
               "noop_s": noop, "root_status": {"s": status_s, "clean": clean},
               "dvc_index": {"s": index_s, "stages": stages, "files": files}}  # fmt: skip
    root_full = next((r["full_s"] for r in rows if r["pipeline"] == "."), None)
    if not args.no_knobs and root_full:
        knobs = knob_runs(repo, env)
        for name, (seconds, stages) in knobs.items():
            print(f"{name}: {seconds:.1f} s ({stages} stages) = "
                  f"{seconds / root_full:.0%} of the root's full run", flush=True)  # fmt: skip
        figures["knobs"] = {k: {"s": s, "stages": n} for k, (s, n) in knobs.items()}
    return figures


def _floor_figures(floor: Floor) -> dict:
    return {"floor_s": floor.project_s, "physical_floor_s": floor.physical_s,
            "steps": floor.steps, "simulated_steps": floor.simulated_steps,
            "floor_workers": floor.workers}  # fmt: skip


def write_figures(path: Path | None, figures: dict) -> None:
    """--json: the figures of this run (with --floors-only, the floors alone)."""
    if path is not None:
        path.write_text(json.dumps(figures, indent=2, sort_keys=True) + "\n")


if __name__ == "__main__":
    main()
