"""The lab of the protocol-change tests (SPEC §26; tests/test_migration.py and
tests/test_migration_resume.py): the two-environment suite built, pushed to a DVC remote and
committed at this protocol, then the protocol bumped and committed with no pipeline rebuilt;
and what those tests run in its clones."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from suite_repo import SUITE, code_env, copy_built, head_commit, run_folder, serial_built_suite

from oodrl.suite.run import _push
from oodrl.testing.pipeline import environment, run

PIPELINES = [".", "pipeline/cartpole"]
STAMP = Path("src", "oodrl", "metrics", "stamp.py")
#: repo_root -> (the lab's checkout, its remote), made once in this process.
_LAB: dict[Path, tuple[Path, Path]] = {}


def version_of(repo: Path) -> int:
    return int(re.search(r"^PROTOCOL_VERSION = (\d+)", (repo / STAMP).read_text(), re.M)[1])


def migration_lab(tmp_path_factory, repo_root: Path) -> tuple[Path, Path]:
    """A lab's checkout and its DVC remote (a directory): the suite built at this protocol (the
    test run's one serial build, `suite_repo.serial_built_suite`: the locks `oodrl suite run`
    writes too, test_suite_run checks), pushed as `oodrl suite run` pushes a project, and
    committed; then the protocol bumped and committed, no pipeline rebuilt: every pipeline
    pending. Every clone below comes from it, and reads the remote over HTTP, read-only: a clone
    pulls the outputs of the stages the bump left as they were and computes the others, pushing
    nothing. Made once a process (the tests only clone it)."""
    made = _LAB.get(repo_root)
    if made is not None:
        return made
    folder = tmp_path_factory.mktemp("lab")
    built, _ = serial_built_suite(repo_root, head_commit(repo_root), run_folder(tmp_path_factory))
    repo = copy_built(built, folder / "repo")
    remote = folder / "remote"
    remote.mkdir()
    for project in [*PIPELINES, SUITE]:  # each a DVC project of its own
        run(repo / project, "dvc", "remote", "add", "--local", "-d", "lab", str(remote))
        _push(repo / project, code_env(repo))
    run(repo, "git", "add", "-A")
    run(repo, "git", "commit", "-q", "-m", "built")
    stamp = repo / STAMP
    version = version_of(repo)
    stamp.write_text(stamp.read_text().replace(f"PROTOCOL_VERSION = {version}",
                                               f"PROTOCOL_VERSION = {version + 1}"))  # fmt: skip
    run(repo, "git", "commit", "-q", "-am", f"protocol {version + 1}")
    made = _LAB[repo_root] = (repo, remote)
    return made


def clone(source: Path, dest: Path, url: str | None = None) -> Path:
    """A fresh clone (git's files only, an empty DVC cache), whose default DVC remote is `url`
    (in config.local, as docs/how-to/remotes.md says), if any."""
    run(source.parent, "git", "clone", "-q", str(source), str(dest))
    assert not (dest / ".dvc" / "cache").exists()
    if url is not None:
        run(dest, "dvc", "remote", "add", "--local", "-d", "pub", url)
    return dest


def head(repo: Path) -> str:
    return run(repo, "git", "rev-parse", "HEAD").stdout.strip()


def subjects(repo: Path, since: str) -> list[str]:
    """The subjects of the commits after `since`, oldest first."""
    log = run(repo, "git", "log", "--reverse", "--format=%s", f"{since}..HEAD").stdout
    return log.splitlines()


def suite_run(repo: Path, *args: str) -> subprocess.CompletedProcess:
    """`oodrl suite run` in a process of its own, as a maintainer runs it, on the checkout's
    own code (its PROTOCOL_VERSION is the target)."""
    command = [sys.executable, "-m", "oodrl", "suite", "run", "--root", str(repo), *args]
    return subprocess.run(command, env=environment(code_env(repo)), capture_output=True,
                          text=True)  # fmt: skip
