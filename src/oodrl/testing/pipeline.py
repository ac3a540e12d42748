"""Run the real DVC pipeline in a throw-away copy of the project (tests, CI, benchmarks).

The copy gets the project's tracked and untracked-not-ignored files (so pipeline outputs and
caches stay behind), its own `git init` and commit, and optionally other params. The
committed dvc.lock comes along, so a train_policy stage whose params are unchanged is skipped.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import yaml

#: The `tiers` block of tiny test pipelines: the fewest calibration streams α = 0.05 allows
#: under the marginal rule, a handful of audit and tier streams, a two-probe tier search on two
#: common episodes and one verification batch of two episodes a tier (the fewest batches that
#: verify every tier: at most 12 search and verification episodes a fault). Two episodes
#: measure R̃ to tenths, not to the protocol's ±0.02: a target of ±1 lets the tiny tiers be
#: verified (and stops the verification after one batch a tier); the random policy's return is
#: measured on two episodes too.
TINY_TIERS: dict[str, Any] = {
    "grid": [0.5, 1.0],
    "episodes": 2,
    "n_calibration": 19,
    "threshold_rule": "episode_max",
    "n_audit": 4,
    "n_streams": 3,
    "search": {
        "search_episodes": 2,
        "max_probes": 2,
        "verify_batch": 2,
        "max_verify_batches": 4,
        "ci_target": 1.0,
        "random_episodes": 2,
    },
}


def project_files(root: Path) -> list[str]:
    listed = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
        cwd=root,
        check=True,
        capture_output=True,
    ).stdout.decode()
    return sorted(f for f in listed.split("\0") if f and (root / f).is_file())


def environment(extra: dict[str, str] | None = None) -> dict[str, str]:
    """The environment stage commands run with in a copy (plus `extra`)."""
    env = {**os.environ, **(extra or {})}
    # Stage commands call `oodrl`: make the running interpreter's scripts win on PATH.
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env.setdefault("GIT_AUTHOR_NAME", "oodrl")
    env.setdefault("GIT_AUTHOR_EMAIL", "oodrl@localhost")
    env.setdefault("GIT_COMMITTER_NAME", "oodrl")
    env.setdefault("GIT_COMMITTER_EMAIL", "oodrl@localhost")
    env["DVC_NO_ANALYTICS"] = "1"
    return env


def run(
    repo: Path, *args: str, check: bool = True, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess:
    """Run a command in the copy (DVC through the current interpreter), `env` added."""
    command = [sys.executable, "-m", "dvc", *args[1:]] if args[0] == "dvc" else list(args)
    done = subprocess.run(command, cwd=repo, env=environment(env), capture_output=True, text=True)
    if check and done.returncode != 0:
        raise RuntimeError(
            f"`{' '.join(args)}` failed with exit code {done.returncode}:\n"
            f"{done.stdout[-4000:]}\n{done.stderr[-4000:]}"
        )
    return done


def edit_params(
    repo: Path, edit: Callable[[dict[str, Any]], None], name: str = "params.yaml"
) -> None:
    """Let `edit` change `repo`'s params file `name` in place (its keys keep their order)."""
    path = repo / name
    params = yaml.safe_load(path.read_text())
    edit(params)
    path.write_text(yaml.safe_dump(params, sort_keys=False))


def copy_project(source: Path, dest: Path, params: dict[str, Any] | None = None) -> Path:
    """A fresh git + DVC repository holding the project, with `params` as params.yaml."""
    for name in project_files(source):
        target = dest / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(source / name, target)
    run(dest, "git", "init", "-q")
    if params is not None:
        from oodrl.suite.pipeline import write

        (dest / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
        write(dest)  # other benchmark lists: other detectors' DVC files
        prune_locks([dest])  # what a copy with its own params builds is the root
    run(dest, "git", "add", "-A")
    run(dest, "git", "commit", "-q", "-m", "copy of the project")
    return dest


def repro(repo: Path, *args: str, env: dict[str, str] | None = None) -> list[str]:
    """`dvc repro`; returns the names of the stages that ran."""
    done = run(repo, "dvc", "repro", *args, env=env)
    return sorted(
        line.split("'")[1]
        for line in done.stdout.splitlines()
        if line.startswith("Running stage '")
    )


def lock_hashes(repo: Path) -> dict[str, str]:
    """Output path -> md5 recorded in the root pipeline's locks (its content addresses)."""
    from oodrl.io.layout import DETECTOR_PIPELINES

    hashes = {}
    for path in [repo / "dvc.lock", *sorted((repo / DETECTOR_PIPELINES).glob("*/dvc.lock"))]:
        for stage in yaml.safe_load(path.read_text())["stages"].values():
            for out in stage.get("outs", []):
                hashes[out["path"]] = out["md5"]
    return hashes


def prune_locks(projects: Iterable[Path]) -> None:
    """Keep in each dvc.lock of these DVC projects (in a copy) only the stages its DVC file
    defines.

    Params that cut the benchmark leave the other stages' entries in the committed locks, and
    DVC keeps them, parsing and rewriting a project's whole dvc.lock after every stage it runs
    (a round trip in pure Python): the tiny suite's build takes a quarter less CPU pruned
    (benchmarks/lock_prune.py). The names come from DVC's own resolver of a DVC file (its
    `foreach` expanded), not from DVC's index, which parses every lock as well. A lock is read
    with libyaml first, and only one naming a stage its DVC file does not define is edited, by
    DVC's own round trip (a PyYAML one would read `5e-05` as a string, and the params as
    changed): a second or so a lock, which done for every lock of the 22 projects made a copy
    take minutes."""
    from dvc.parsing import DataResolver
    from dvc.repo import Repo
    from dvc.utils.serialize import modify_yaml

    from oodrl.io import yamlio
    from oodrl.io.layout import DETECTOR_PIPELINES

    for project in projects:
        dvc_files = [
            project / "dvc.yaml",
            *sorted(project.glob(f"{DETECTOR_PIPELINES}/*/dvc.yaml")),
        ]
        with Repo(str(project.resolve())) as dvc:
            for dvc_file in [f for f in dvc_files if f.with_suffix(".lock").is_file()]:
                data = yamlio.load(dvc_file.read_text())
                wdir = str(dvc_file.parent.resolve())
                defined = set(DataResolver(dvc, wdir, data).get_keys())
                lock = dvc_file.with_suffix(".lock")
                if set(yamlio.load(lock.read_text()).get("stages") or {}) <= defined:
                    continue
                with modify_yaml(lock) as document:
                    for name in [name for name in document["stages"] if name not in defined]:
                        del document["stages"][name]
