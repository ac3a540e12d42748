"""Small results are git-tracked outputs (SPEC §21): each committed one is the file its project's
committed dvc.lock records, byte for byte (DVC's md5 of a file is that of its bytes), so a clone
shows the numbers the locks stand for without computing anything."""

from __future__ import annotations

import hashlib
import json
import subprocess
from pathlib import Path

import yaml

from oodrl.suite.pipeline import pipeline_dirs


def _tracked(repo_root: Path) -> set[str]:
    listing = subprocess.run(["git", "ls-files"], cwd=repo_root, capture_output=True, text=True)
    return set(listing.stdout.splitlines())


def _locked_files(project: Path) -> dict[str, str]:
    """Output path (from the project) → md5, for every file output its dvc.lock records."""
    lock = project / "dvc.lock"
    stages = yaml.safe_load(lock.read_text())["stages"] if lock.is_file() else {}
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


def test_every_committed_lock_records_the_sources_of_this_commit(repo_root):
    """check_params depends on oodrl's sources (an environment's project on each file, the root
    on the directory): a commit that edits one and not the locks leaves every clone's `dvc repro`
    re-running check_params and rewriting dvc.lock. The environments' file hashes are compared
    here; the root's directory hash by DVC itself."""
    stale = []
    for project in pipeline_dirs(repo_root)[1:]:
        stage = yaml.safe_load((project / "dvc.lock").read_text())["stages"]["check_params"]
        for dep in stage["deps"]:
            path = project / dep["path"]
            if path.is_dir():  # a directory's hash is DVC's own
                continue
            if not path.is_file() or hashlib.md5(path.read_bytes()).hexdigest() != dep["md5"]:
                stale.append(f"{project.name}: {dep['path']}")
    assert not stale, f"relock check_params (dvc repro -s check_params) in: {stale[:5]}"
    done = subprocess.run(
        ["dvc", "status", "--json", "check_params"], cwd=repo_root, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    changes = json.loads(done.stdout).get("check_params", [])
    assert not [c for c in changes if isinstance(c, dict) and "changed deps" in c], changes
