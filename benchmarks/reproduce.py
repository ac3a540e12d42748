"""Prove the pipeline reproduces on other machines: from-scratch runs under different math
kernels give identical outputs (SPEC §14).

    python benchmarks/reproduce.py --params ci/params.yaml

For each kernel selection of `oodrl.testing.kernels` (this CPU's own kernels, an AVX2 machine's,
an SSE4.2 machine's), a fresh copy of the project (own git + DVC repo, no data) builds the
pipeline with the libraries' kernels forced; then every file of every output in the dvc.lock
files must be identical. The first selection builds by `dvc repro`, which must leave `dvc status
-q` clean and a further `dvc repro` with no stage to run. The others replay the stage commands
that run ran, in its order and as DVC runs them (the same shell command, working folder and
DVC_STAGE, so the same warm stage server), without DVC's bookkeeping: on these tiny params that
bookkeeping is more than half of a run (docs/performance.md) and cannot change a byte the
stages write, which is what differs between kernels if anything does.
Exit code 1 on any difference. Detectors not certified machine-independent (library ones, SPEC
§17) are left out of the copied params and named; benchmarks/library_kernels.py reports on them.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from oodrl.config import read_params_data
from oodrl.testing.kernels import certified_only, kernel_selections
from oodrl.testing.pipeline import copy_project, environment, lock_hashes, repro, run

ROOT = Path(__file__).resolve().parents[1]


def ran_in_order(repo: Path, env: dict[str, str]) -> list[str]:
    """`dvc repro`; the stages that ran, in the order DVC ran them."""
    done = run(repo, "dvc", "repro", env=env)
    prefix = "Running stage '"
    return [line.split("'")[1] for line in done.stdout.splitlines() if line.startswith(prefix)]


def stage_commands(repo: Path, names: list[str]) -> list[tuple[str, Path, str]]:
    """(name, working folder relative to `repo`, shell command) of each named stage."""
    from dvc.repo import Repo

    with contextlib.chdir(repo), Repo(".") as dvc:  # names are relative to the repository
        stages = {stage.addressing: stage for stage in dvc.index.stages}
        return [
            (name, Path(stages[name].wdir).relative_to(Path.cwd()), stages[name].cmd)
            for name in names
        ]


def replay(repo: Path, commands: list[tuple[str, Path, str]], env: dict[str, str]) -> None:
    """Run each stage command in `repo` as DVC runs it (raises on the first that fails)."""
    for name, wdir, command in commands:
        stage_env = environment({**env, "DVC_ROOT": str(repo), "DVC_STAGE": name})
        done = subprocess.run(
            command, shell=True, cwd=repo / wdir, env=stage_env, capture_output=True, text=True
        )
        if done.returncode != 0:
            raise RuntimeError(
                f"stage {name} exited {done.returncode}:\n{done.stdout[-2000:]}\n"
                f"{done.stderr[-2000:]}"
            )


def output_files(repo: Path, outputs: list[str]) -> dict[str, str]:
    """md5 of every file of `outputs` (paths in `repo`, a folder meaning every file in it)."""
    hashes = {}
    for output in outputs:
        path = repo / output
        files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
        for file in files:
            name = file.relative_to(repo).as_posix()
            hashes[name] = hashlib.md5(file.read_bytes()).hexdigest() if file.exists() else ""
    return hashes


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", type=Path, default=ROOT / "ci" / "params.yaml")
    args = parser.parse_args()
    # Merged: the copy has no base file beside it. Only certified detectors are promised.
    params, left_out = certified_only(read_params_data(args.params))
    if left_out:
        print(f"Left out, not certified machine-independent: {', '.join(left_out)}")
    runs = {}
    commands, outputs = [], []
    with tempfile.TemporaryDirectory(prefix="oodrl-reproduce-") as scratch:
        for name, selection in kernel_selections().items():
            repo = copy_project(ROOT, Path(scratch) / name, params)
            start = time.perf_counter()
            if not commands:
                ran = ran_in_order(repo, selection)
                how = f"dvc repro ran {len(ran)} stages"
                commands, outputs = stage_commands(repo, ran), sorted(lock_hashes(repo))
            else:
                try:
                    replay(repo, commands, selection)
                except RuntimeError as error:
                    print(f"FAIL: {name}: {error}")
                    return 1
                how = f"its {len(commands)} stage commands replayed"
            print(f"{name} kernels: {how} in {time.perf_counter() - start:.1f} s", flush=True)
            if len(runs) == 0:
                status = run(
                    repo, "dvc", "status", "-q", "--with-deps", "dvc.yaml", check=False,
                    env=selection,
                )  # fmt: skip
                if status.returncode != 0:
                    print(f"FAIL: {name}: `dvc status -q` exit {status.returncode}")
                    return 1
                if again := repro(repo, env=selection):
                    print(f"FAIL: {name}: a second dvc repro re-ran {again}")
                    return 1
            runs[name] = output_files(repo, outputs)
    reference_name, reference = next(iter(runs.items()))
    for name, hashes in runs.items():
        differing = sorted(
            p for p in reference.keys() | hashes.keys() if reference.get(p) != hashes.get(p)
        )
        if differing:
            print(
                f"FAIL: {len(differing)} files differ between the {reference_name} and "
                f"{name} runs: {differing[:20]}"
            )
            return 1
    print(
        f"OK: {len(reference)} files of {len(outputs)} outputs byte-identical across "
        f"{len(runs)} from-scratch runs under kernel selections {', '.join(runs)}; "
        f"dvc status clean and a second repro ran nothing after the {reference_name} one"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
