"""A copy of the project whose suite is a subset of the environments (tests, benchmarks).

The copy holds one commit (git archive, so edits in the working tree stay behind), its own
`git init` and commit, edited params, and only the chosen pipelines: the other environments'
directories are dropped and `oodrl.suite.environments.PIPELINE_DIRS` in the copy's sources lists the
kept ones, so its leaderboard reads those alone. Stage commands must run the copy's code
(`code_env`).
"""

from __future__ import annotations

import io
import re
import shutil
import subprocess
import tarfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from oodrl.suite.pipeline import project_dirs
from oodrl.testing.pipeline import edit_params, prune_locks, repro, run

SUITE = "pipeline/suite"
SUITE_PARAMS = "pipeline/params.yaml"
ParamsEdit = Callable[[dict[str, Any]], None]


def head_commit(source: Path) -> str:
    """The commit to copy: resolved once, as others may commit while a copy is made."""
    done = subprocess.run(["git", "rev-parse", "HEAD"], cwd=source, capture_output=True, check=True)
    return done.stdout.decode().strip()


def code_env(repo: Path) -> dict[str, str]:
    """Stage commands run the copy's own sources, whatever oodrl is installed."""
    return {"PYTHONPATH": str(repo / "src")}


def suite_copy(
    source: Path,
    commit: str,
    dest: Path,
    pipelines: list[str],
    edit: ParamsEdit | None = None,
    edit_environment: ParamsEdit | None = None,
    edit_suite: ParamsEdit | None = None,
) -> Path:
    """`commit` of `source` in `dest` with the suite cut to `pipelines` ('.' is the root);
    `edit` changes the root's params.yaml, `edit_suite` the suite's (pipeline/params.yaml, which
    every environment extends), `edit_environment` each kept environment's own."""
    dest.mkdir(parents=True)
    archive = subprocess.run(
        ["git", "archive", commit], cwd=source, capture_output=True, check=True
    )
    with tarfile.open(fileobj=io.BytesIO(archive.stdout)) as tar:
        tar.extractall(dest, filter="data")
    for directory in sorted(d for d in (dest / "pipeline").iterdir() if d.is_dir()):
        name = directory.relative_to(dest).as_posix()
        if name == SUITE:
            continue
        if name not in pipelines:
            shutil.rmtree(directory)
        elif edit_environment is not None:
            edit_params(directory, edit_environment)
    if edit is not None:
        edit_params(dest, edit)
    if edit_suite is not None:
        edit_params(dest, edit_suite, SUITE_PARAMS)
    _cut_suite_list(dest / "src" / "oodrl" / "suite" / "environments.py", pipelines)
    run(dest, "oodrl", "pipeline", "write", env=code_env(dest))
    run(dest, "git", "init", "-q")
    prune_locks(p for p in project_dirs(dest) if (p / ".dvc").is_dir())  # the kept ones
    run(dest, "git", "add", "-A")
    run(dest, "git", "commit", "-q", "-m", f"the suite of {', '.join(pipelines)}")
    return dest


def _cut_suite_list(suite_module: Path, pipelines: list[str]) -> None:
    """Keep the PIPELINE_DIRS and MORE_POLICIES entries whose directory is in `pipelines`."""
    entry = re.compile(r'Path\("([^"]+)"\)')

    def kept(match: re.Match) -> str:
        lines = match[2].splitlines(keepends=True)
        found = [(line, entry.search(line)) for line in lines]
        kept_lines = [line for line, e in found if e is None or e[1] in pipelines]
        return match[1] + "".join(kept_lines) + match[3]

    text = suite_module.read_text()
    for name in ("PIPELINE_DIRS", "MORE_POLICIES"):  # one entry a line, or an empty {}
        block = re.compile(rf"({name}: dict\[[^\n]*\] = \{{)(.*?)(\}}\n)", re.S)
        text, found = block.subn(kept, text, count=1)
        if found != 1:
            raise RuntimeError(f"{suite_module}: no {name} block to cut")
    suite_module.write_text(text)


def serial_build(repo: Path, pipelines: list[str]) -> dict[str, tuple[float, list[str]]]:
    """The reference build: `dvc repro` of each pipeline's project in turn, then the suite's;
    project → (seconds, stages that ran)."""
    import time

    built = {}
    for project in [*pipelines, SUITE]:
        start = time.perf_counter()
        ran = repro(repo / project, env=code_env(repo))
        built[project] = (time.perf_counter() - start, ran)
    return built


def locks(repo: Path) -> dict[str, bytes]:
    """Every dvc.lock of the repository, by path."""
    return {p.relative_to(repo).as_posix(): p.read_bytes() for p in sorted(repo.rglob("dvc.lock"))}
