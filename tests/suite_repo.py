"""A suite of two environments (LunarLander at the root, CartPole) at tiny params, in a fresh
git + DVC repository holding the project's last commit: what `oodrl suite run` and the DVC
remote tests build. Stage commands run the copy's own code (PYTHONPATH), so edits other
people have in the working tree never reach a test build."""

from __future__ import annotations

import io
import re
import shutil
import subprocess
import tarfile
from pathlib import Path

import yaml

from oodrl.testing.pipeline import repro, run

KEPT = {"LunarLander-v3": ".", "CartPole-v1": "pipeline/cartpole"}
PIPELINES = list(KEPT.values())
SUITE = "pipeline/suite"


def code_env(repo: Path) -> dict[str, str]:
    return {"PYTHONPATH": str(repo / "src")}


def head_commit(source: Path) -> str:
    """The commit to copy: resolved once, as others may commit while the tests run."""
    git = ["git", "rev-parse", "HEAD"]
    return subprocess.run(
        git, cwd=source, capture_output=True, text=True, check=True
    ).stdout.strip()


def two_environment_suite(source: Path, commit: str, dest: Path) -> Path:
    """`source`'s `commit` in `dest` (git init, one commit): root and CartPole, one detector
    and one injector, T=60, a handful of episodes."""
    dest.mkdir(parents=True)
    archive = subprocess.run(
        ["git", "archive", commit], cwd=source, capture_output=True, check=True
    )
    with tarfile.open(fileobj=io.BytesIO(archive.stdout)) as tar:
        tar.extractall(dest, filter="data")
    for directory in (dest / "pipeline").iterdir():
        if directory.relative_to(dest).as_posix() not in (*PIPELINES, SUITE):
            shutil.rmtree(directory)
    params = yaml.safe_load((dest / "params.yaml").read_text())
    params["env"]["T"] = 60
    params["data"].update(n_id=4, n_ood=3)
    params["anomaly"]["sweep"] = [0.5]
    params["benchmark"] = {"detectors": ["mahalanobis_distance"], "injectors": ["stuck_actuator"]}
    params["metrics"].update(n_boot=20, traces_per_anomaly=1)
    params["executor"]["workers"] = 1
    (dest / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    cartpole = dest / "pipeline/cartpole/params.yaml"
    local = yaml.safe_load(cartpole.read_text())
    local["env"] = {**local.get("env", {}), "T": 60, "onset": None}
    cartpole.write_text(yaml.safe_dump(local, sort_keys=False))
    # The leaderboard reads the environments of oodrl.suite: this copy's suite has two.
    suite = dest / "src/oodrl/suite.py"
    kept = "".join(f'    "{env}": Path("{d}"),\n' for env, d in KEPT.items())
    block = re.compile(r"(PIPELINE_DIRS: dict\[str, Path\] = \{\n).*?(\}\n)", re.S)
    text, found = block.subn(lambda m: m[1] + kept + m[2], suite.read_text(), count=1)
    assert found == 1, "oodrl.suite.PIPELINE_DIRS moved; update tests/suite_repo.py"
    suite.write_text(text)
    run(dest, "oodrl", "pipeline", "write", env=code_env(dest))
    run(dest, "git", "init", "-q")
    run(dest, "git", "add", "-A")
    run(dest, "git", "commit", "-q", "-m", "a suite of two environments, tiny params")
    return dest


def serial_suite(repo: Path) -> list[str]:
    """The reference: `dvc repro` of each project in turn, then the suite's; what ran."""
    env = code_env(repo)
    return [f"{p}:{s}" for p in [*PIPELINES, SUITE] for s in repro(repo / p, env=env)]


def locks(repo: Path) -> dict[str, bytes]:
    """Every dvc.lock of the repository, by path."""
    return {p.relative_to(repo).as_posix(): p.read_bytes() for p in sorted(repo.rglob("dvc.lock"))}


def checkout(repo: Path) -> dict[Path, bytes]:
    """Every file of the checkout but git's and DVC's own scratch (.dvc/tmp: locks, indexes)."""
    files = (path for path in repo.rglob("*") if path.is_file() and not _scratch(path))
    return {path: path.read_bytes() for path in files}


def _scratch(path: Path) -> bool:
    pairs = zip(path.parts, path.parts[1:], strict=False)
    return ".git" in path.parts or any(pair == (".dvc", "tmp") for pair in pairs)
