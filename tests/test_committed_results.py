"""Small results are git-tracked outputs (SPEC §21): each committed one is the file its project's
committed dvc.lock records, byte for byte (DVC's md5 of a file is that of its bytes), so a clone
shows the numbers the locks stand for without computing anything; pending projects' too, during a
change of protocol (SPEC §26)."""

from __future__ import annotations

import hashlib
import subprocess
from pathlib import Path

from oodrl.errors import ConfigError
from oodrl.io import yamlio
from oodrl.suite import migration
from oodrl.suite.pipeline import pipeline_dirs


def _tracked(repo_root: Path) -> set[str]:
    listing = subprocess.run(["git", "ls-files"], cwd=repo_root, capture_output=True, text=True)
    return set(listing.stdout.splitlines())


def _locked_files(project: Path) -> dict[str, str]:
    """Output path (from the project) → md5, for every file output its dvc.lock records."""
    lock = project / "dvc.lock"
    # libyaml: the 22 projects' locks are 2 MB, 5 s of PyYAML's pure-Python loader
    stages = yamlio.load(lock.read_text())["stages"] if lock.is_file() else {}
    return {
        out["path"]: out["md5"]
        for stage in stages.values()
        for out in stage.get("outs", [])
        if not out["md5"].endswith(".dir")
    }


def test_every_committed_result_is_the_file_its_lock_records(repo_root):
    tracked, checked = _tracked(repo_root), 0
    for project in [*pipeline_dirs(repo_root), repo_root / "pipeline" / "suite"]:
        for path, md5 in _locked_files(project).items():
            name = (project / path).relative_to(repo_root).as_posix()
            if name in tracked:
                data = (project / path).read_bytes()
                assert hashlib.md5(data).hexdigest() == md5, f"{name} is not what its lock records"
                checked += 1
    assert checked > 0, "no committed result was checked"


def test_every_project_is_current_or_pending_in_a_change_of_protocol(repo_root):
    """Every project's committed locks are what `dvc repro` keeps (check_params' deps, the
    source files and directory and the params files, as locked; every stage's command, deps,
    params values and code stamps as its lock records), or its results are stamped at an older
    protocol than this code's (SPEC §26). A commit that edits the sources without relocking
    check_params fails here, naming each project and the file: every clone's `dvc repro` would
    re-run check_params and rewrite dvc.lock. The root's directory hash is DVC's own (checked
    against `dvc status` in tests/test_migration_state.py)."""
    try:
        states = migration.check(repo_root)
    except ConfigError as error:
        raise AssertionError(str(error)) from None
    assert {state.status for state in states} <= {migration.CURRENT, migration.PENDING}
    assert all(
        state.built_version < migration.target_version()
        for state in states
        if state.status == migration.PENDING
    )
