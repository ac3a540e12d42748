"""A suite published read-only (SPEC §21): a lab builds it with a directory remote and serves
that directory over HTTP (`python -m http.server`: GET and HEAD only); a fresh clone with only
the HTTP remote runs `oodrl suite run`, which restores what the remote has, builds what it lacks
locally and pushes nothing (the served directory's files stay as they were).

The repository is the suite's shape at its smallest (as tests/hostile/test_suite_run_hostile.py):
the root's DVC project, one pipeline's (pipeline/a, with a params knob) and the leaderboard's
(pipeline/suite). The root has the shape of protocol 3's impact stages: two stages each writing
one file of data/impact, and a stage reading the directory, which `dvc repro --pull
--allow-missing` gets wrong on a fresh clone (the last tests); `published_as_oodrl` has
protocol 4's, the reading stage naming each file."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import socket
from pathlib import Path

import pytest
from tiny_suite import STAMP, assert_checking_line_then_the_error, dvc, dvc_project, git
from typer.testing import CliRunner

from oodrl.cli import app
from oodrl.suite import run as suite_run
from oodrl.suite.run import SuiteRunError, run_suite

pytestmark = pytest.mark.slow

#: The results' stages end with STAMP (this code's protocol): a built project reads as current.
TIERS = json.dumps(f"mkdir -p reports && cat data/impact/x.yaml data/impact/y.yaml > "
                   f"reports/results.yaml && {STAMP}")  # fmt: skip
ROOT = f"""\
  impact:
    foreach: [x, y]
    do:
      cmd: mkdir -p data/impact && echo ${{item}} > data/impact/${{item}}.yaml
      outs:
        - data/impact/${{item}}.yaml
  tiers:
    cmd: {TIERS}
    deps:
      - data/impact
    outs:
      - reports/results.yaml
"""
#: The root as protocol 4 has it: every dep names one stage's output.
ROOT_BY_FILE = ROOT.replace(
    "      - data/impact\n", "      - data/impact/x.yaml\n      - data/impact/y.yaml\n"
)
PIPELINE = f"""\
  build:
    cmd: {json.dumps(f"mkdir -p reports && echo pipeline a > reports/results.yaml && {STAMP}")}
    params:
      - knob
    outs:
      - reports/results.yaml
"""
LEADERBOARD = """\
  leaderboard:
    cmd: (echo leaderboard; cat ../a/reports/results.yaml) > leaderboard.txt
    deps:
      - ../a/reports/results.yaml
    outs:
      - leaderboard.txt
"""
#: Every output of the suite, by path from the root.
OUTPUTS = ("data/impact/x.yaml", "data/impact/y.yaml", "reports/results.yaml",
           "pipeline/a/reports/results.yaml", "pipeline/suite/leaderboard.txt")  # fmt: skip


def _listing(directory: Path) -> dict[str, bytes]:
    return {p.relative_to(directory).as_posix(): p.read_bytes() for p in directory.rglob("*")
            if p.is_file()}  # fmt: skip


@pytest.fixture(scope="module")
def published(tmp_path_factory) -> tuple[Path, Path]:
    """A lab's checkout, built by `oodrl suite run` with a directory remote and committed, and
    that remote (every output and run-cache entry pushed)."""
    return _publish(tmp_path_factory.mktemp("published"))


@pytest.fixture(scope="module")
def published_as_oodrl(tmp_path_factory) -> tuple[Path, Path]:
    """`published` in protocol 4's shape (SPEC §23): `tiers` reads each file of data/impact, one
    stage's output each, never the directory (whose DVC hash would count the .gitignore DVC
    writes inside it: oodrl.suite.migration finds the root stale on `published`, "tiers:
    data/impact changed")."""
    return _publish(tmp_path_factory.mktemp("published-as-oodrl"), root=ROOT_BY_FILE)


def _publish(lab: Path, root: str = ROOT) -> tuple[Path, Path]:
    repo, remote = lab / "repo", lab / "remote"
    dvc_project(repo, None, root)
    dvc_project(repo / "pipeline" / "a", "../../../.dvc/cache", PIPELINE)
    (repo / "pipeline" / "a" / "params.yaml").write_text("knob: 1\n")
    dvc_project(repo / "pipeline" / "suite", "../../../.dvc/cache", LEADERBOARD)
    git(repo, "init", "-q")
    git(repo, "add", "-A")
    git(repo, "commit", "-q", "-m", "a tiny suite")
    remote.mkdir()
    dvc(repo, "remote", "add", "--local", "-d", "lab", str(remote))
    run_suite(repo, workers=2, echo=lambda line: None)
    git(repo, "add", "-A")
    git(repo, "commit", "-q", "-m", "built")
    assert not set(OUTPUTS) & set(git(repo, "ls-files").split())  # DVC's .gitignore came too
    return repo, remote


def clone_with_remote(lab: Path, clone: Path, url: str) -> Path:
    """A fresh clone whose only remote is `url`, the default, in config.local (as the how-to)."""
    git(lab.parent, "clone", "-q", str(lab), str(clone))
    dvc(clone, "remote", "add", "--local", "-d", "pub", url)
    return clone


def ran(run) -> dict[str, tuple[str, ...]]:
    return {built.pipeline: built.ran for built in run.pipelines}


def test_a_fresh_clone_restores_the_suite_and_builds_only_a_changed_knob(
    published_as_oodrl, serve, tmp_path
):
    lab, remote = published_as_oodrl
    url = serve(remote)
    served = _listing(remote)
    clone = clone_with_remote(lab, tmp_path / "clone", url)

    result = CliRunner().invoke(app, ["suite", "run", "--root", str(clone), "--workers", "2"])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert lines[1] == (f"suite: remote 'pub' ({url}) is read-only (HTTP): restoring from it, "
                        f"building what it lacks locally, pushing nothing")  # fmt: skip
    finished = [line for line in lines if line.startswith("finished")]
    assert len(finished) == 2 and all(line.endswith("(0 stages ran)") for line in finished)
    assert lines[-1].endswith("the head ran nothing")
    assert git(clone, "status", "--porcelain", "--untracked-files=all") == ""
    assert {path: (clone / path).read_bytes() for path in OUTPUTS} == {
        path: (lab / path).read_bytes() for path in OUTPUTS
    }
    assert _listing(remote) == served

    # A knob edit, committed: its stage alone runs (its output is unchanged: not the leaderboard);
    # the root, current, is not cloned again.
    (clone / "pipeline" / "a" / "params.yaml").write_text("knob: 2\n")
    git(clone, "commit", "-q", "-am", "knob: 2")
    lines = []
    run = run_suite(clone, workers=2, echo=lines.append)
    assert lines[1].startswith("suite: remote 'pub'") and "pushing nothing" in lines[1]
    assert "suite: 1 of 2 pipelines are up to date; building the other 1" in lines
    assert ran(run) == {"pipeline/a": ("build",)}
    assert run.head_ran == ()
    assert git(clone, "status", "--porcelain") == " M pipeline/a/dvc.lock\n"
    assert _listing(remote) == served


def test_what_the_remote_lacks_is_built_locally_and_not_pushed(published, serve, tmp_path):
    lab, remote = published
    partial = tmp_path / "partial"
    shutil.copytree(remote, partial)
    for path in ("data/impact/y.yaml", "pipeline/a/reports/results.yaml"):
        digest = hashlib.md5((lab / path).read_bytes()).hexdigest()  # its object's name
        (partial / "files" / "md5" / digest[:2] / digest[2:]).unlink()
    served = _listing(partial)
    clone = clone_with_remote(lab, tmp_path / "clone", serve(partial))

    run = run_suite(clone, workers=2, echo=lambda line: None)
    assert ran(run) == {".": ("impact@y",), "pipeline/a": ("build",)}
    assert run.head_ran == ()
    assert git(clone, "status", "--porcelain", "--untracked-files=all") == ""
    assert {path: (clone / path).read_bytes() for path in OUTPUTS} == {
        path: (lab / path).read_bytes() for path in OUTPUTS
    }
    assert _listing(partial) == served


def test_a_directory_remote_that_refuses_writes_is_read_only(published, tmp_path, monkeypatch):
    """A write refused for permission (a read-only mount, a bucket without write access; as root
    a directory's mode refuses nothing, so the refusal is simulated) makes the run read-only."""
    from dvc_objects.fs.local import LocalFileSystem

    def refuse(self, path, *args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", path)

    lab, remote = published
    served = _listing(remote)
    clone = clone_with_remote(lab, tmp_path / "clone", str(remote))
    monkeypatch.setattr(LocalFileSystem, "pipe_file", refuse)
    lines: list[str] = []
    run = run_suite(clone, workers=2, echo=lines.append)
    assert lines[1].startswith(f"suite: remote 'pub' ({remote}) is read-only (it refuses a write")
    assert lines[1].endswith(": restoring from it, building what it lacks locally, pushing nothing")
    assert ran(run) == {".": (), "pipeline/a": ()}
    assert _listing(remote) == served


def test_a_remote_failing_the_probe_otherwise_is_refused(published, tmp_path, monkeypatch):
    from dvc_objects.fs.local import LocalFileSystem

    def fail(self, path, *args, **kwargs):
        raise OSError(errno.EIO, "Input/output error")

    lab, remote = published
    monkeypatch.setattr(LocalFileSystem, "pipe_file", fail)
    with pytest.raises(SuiteRunError, match=r"\(.*\) fails a probe write: \[Errno 5\] Input/"):
        suite_run._check_remote(lab, suite_run.default_remote(lab))


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_an_http_remote_that_does_not_answer_is_refused(published, tmp_path):
    url = f"http://127.0.0.1:{_free_port()}/"
    clone = clone_with_remote(published[0], tmp_path / "clone", url)
    result = CliRunner().invoke(app, ["suite", "run", "--root", str(clone)])
    assert result.exit_code == 1, result.output
    assert_checking_line_then_the_error(result.output)
    assert f"DVC remote 'pub' ({url}) does not answer: [Errno 111] Connection refused" in (
        result.output
    )
    assert git(clone, "status", "--porcelain", "--untracked-files=all") == ""


def test_ray_with_a_read_only_remote_is_refused(published, serve, tmp_path, monkeypatch):
    lab, remote = published
    clone = clone_with_remote(lab, tmp_path / "clone", serve(remote))
    monkeypatch.setattr(suite_run, "_check_reachable", lambda address: None)  # a live cluster
    result = CliRunner().invoke(
        app, ["suite", "run", "--root", str(clone), "--ray", "127.0.0.1:6379"]
    )
    assert result.exit_code == 2, result.output
    assert_checking_line_then_the_error(result.output)
    assert "--ray: the nodes share stages through a DVC remote and 'pub' is read-only (HTTP); " in (
        result.output
    )


def test_dvc_repro_allow_missing_runs_a_stage_on_a_directory_it_never_pulled(
    published, serve, tmp_path
):
    """Why oodrl's projects ignore whole a directory that several stages fill (FILLED_DIRS), and
    why `oodrl suite run` pulls first: here DVC committed a .gitignore inside data/impact, and
    DVC's own `dvc repro --pull --allow-missing`, with nothing changed, skips the impact stages
    (outputs missing, but allowed) without pulling them, then finds `tiers`'s dep data/impact
    modified, not missing (git made it, for that .gitignore), and runs it on an empty
    directory. After a `dvc pull`, `dvc repro --pull` runs nothing."""
    lab, remote = published
    clone = clone_with_remote(lab, tmp_path / "clone", serve(remote))
    assert sorted(os.listdir(clone / "data" / "impact")) == [".gitignore"]
    done = dvc(clone, "repro", "--pull", "--allow-missing", check=False)
    assert done.returncode != 0
    assert "Stage 'impact@x' didn't change, skipping" in done.stdout
    assert "Running stage 'tiers'" in done.stdout
    assert "data/impact/x.yaml: No such file or directory" in done.stderr

    fresh = clone_with_remote(lab, tmp_path / "fresh", serve(remote))
    dvc(fresh, "pull", "--allow-missing", "-q")
    done = dvc(fresh, "repro", "--pull")
    assert suite_run.ran_stages(done.stdout) == ()


def test_after_an_edit_dvc_repro_pull_runs_only_the_changed_stage(published, serve, tmp_path):
    """The remotes how-to's way after an edit in a fresh clone: `dvc repro --pull` without
    `--allow-missing` pulls every unchanged stage's outputs (impact@x, impact@y) before the
    changed stage (tiers) reads them, and runs that stage alone; the remote stays as it was."""
    lab, remote = published
    served = _listing(remote)
    clone = clone_with_remote(lab, tmp_path / "clone", serve(remote))
    pipeline = clone / "dvc.yaml"
    edited = "> reports/r.tmp && mv reports/r.tmp reports/results.yaml"  # the same output
    # The first `> reports/results.yaml`, tiers' `cat` (STAMP's `>>` after it stays as it is).
    pipeline.write_text(pipeline.read_text().replace("> reports/results.yaml", edited, 1))
    done = dvc(clone, "repro", "--pull")
    assert suite_run.ran_stages(done.stdout) == ("tiers",)
    assert (clone / "reports" / "results.yaml").read_bytes() == (
        lab / "reports" / "results.yaml"
    ).read_bytes()
    assert _listing(remote) == served
