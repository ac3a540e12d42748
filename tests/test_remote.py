"""A shared DVC remote (SPEC §16): a fresh clone gets every result by `dvc pull`, and a second
machine's `dvc repro` restores stages from the run-cache instead of recomputing them, against a
real S3-API server on loopback (moto's server, as DVC's S3 plugin is tested); a directory remote
read over HTTP by a fresh clone's `dvc repro --pull --allow-missing`; a remote whose probe write
fails (a bucket that does not exist) stops `oodrl suite run` in one line, before anything runs."""

from __future__ import annotations

from pathlib import Path

import pytest
from suite_repo import (
    checkout,
    code_env,
    copy_built,
    head_commit,
    locks,
    run_folder,
    serial_built_suite,
    two_environment_suite,
)
from tiny_suite import assert_checking_line_then_the_error
from typer.testing import CliRunner

from oodrl.cli import app
from oodrl.suite.run import ran_stages
from oodrl.testing.pipeline import repro, run

pytestmark = pytest.mark.slow

#: One environment's DVC project: every project of the suite shares a remote the same way.
PROJECT = "pipeline/cartpole"
BUCKET = "oodrl-lab"


@pytest.fixture(scope="module")
def built(tmp_path_factory, repo_root) -> tuple[Path, list[str]]:
    """The suite built (a copy of the serial build a test run makes once,
    suite_repo.serial_built_suite) and its locks committed: HEAD has current locks, HEAD~1 the
    stale ones of a commit nobody has built yet; and the CartPole stages that ran."""
    made, ran = serial_built_suite(repo_root, head_commit(repo_root), run_folder(tmp_path_factory))
    repo = copy_built(made, tmp_path_factory.mktemp("built") / "repo")
    run(repo, "git", "add", "-A")
    run(repo, "git", "commit", "-q", "-m", "the suite built")
    return repo, [stage for stage in ran if stage.startswith(f"{PROJECT}:")]


@pytest.fixture
def s3_server(monkeypatch):
    """moto's S3 server on a free loopback port; the endpoint URL."""
    from moto.server import ThreadedMotoServer

    for name, value in [("AWS_ACCESS_KEY_ID", "testing"), ("AWS_SECRET_ACCESS_KEY", "testing"),
                        ("AWS_DEFAULT_REGION", "us-east-1")]:  # fmt: skip
        monkeypatch.setenv(name, value)
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    yield f"http://{host}:{port}"
    server.stop()


@pytest.fixture
def remote(s3_server) -> dict[str, str]:
    """An S3 remote's `dvc remote add` URL and `dvc remote modify` options. A directory remote
    goes the same way through DVC; its push of every output and run-cache entry, and a fresh
    clone restoring from it, are test_readonly_remote.py's lab (`published`) and this module's
    first test."""
    import boto3

    boto3.client("s3", endpoint_url=s3_server).create_bucket(Bucket=BUCKET)
    return {"url": f"s3://{BUCKET}/oodrl", "endpointurl": s3_server}


def configure(project: Path, remote: dict[str, str]) -> None:
    """As docs/how-to/remotes.md says: the remote in the project's git-ignored config.local."""
    run(project, "dvc", "remote", "add", "--local", "-f", "-d", "lab", remote["url"])
    for option, value in remote.items():
        if option != "url":
            run(project, "dvc", "remote", "modify", "--local", "lab", option, value)


def test_dvc_repro_allow_missing_on_a_fresh_clone_with_a_read_only_remote_runs_nothing(
    built, serve, tmp_path
):
    """DVC's own way to fetch what is unchanged and run what changed, on a fresh clone whose
    only remote is read-only HTTP: nothing changed, so no stage runs and no file changes. It
    can, because git ignores the directories several stages fill whole (FILLED_DIRS): a
    clone has none of them, and a stage reading one finds its dep missing, not modified."""
    repo, _ = built
    shared = tmp_path / "shared"
    configure(repo / PROJECT, {"url": str(shared)})
    run(repo / PROJECT, "dvc", "push", "-q")
    clone = tmp_path / "clone"
    run(tmp_path, "git", "clone", "-q", str(repo), str(clone))
    assert not (clone / PROJECT / "scores").exists()
    configure(clone / PROJECT, {"url": serve(shared)})
    assert repro(clone / PROJECT, "--pull", "--allow-missing", env=code_env(clone)) == []
    assert run(clone, "git", "status", "--porcelain").stdout == ""


def test_a_fresh_clone_pulls_and_a_second_machine_restores(built, remote, tmp_path):
    repo, built_ran = built
    configure(repo / PROJECT, remote)
    run(repo / PROJECT, "dvc", "push", "--run-cache")

    clone = tmp_path / "clone"
    run(tmp_path, "git", "clone", "-q", str(repo), str(clone))
    configure(clone / PROJECT, remote)
    run(clone / PROJECT, "dvc", "pull")
    assert run(clone / PROJECT, "dvc", "status", "--quiet", check=False).returncode == 0
    assert repro(clone / PROJECT, env=code_env(clone)) == []
    results = "reports/results.yaml"
    assert (clone / PROJECT / results).read_bytes() == (repo / PROJECT / results).read_bytes()

    # Another machine on the commit before, whose locks are stale: every stage's run is found
    # in the remote's run-cache and restored, and the locks come out as the build wrote them.
    # Run again: the stages DVC cannot cache (persistent outputs), and those with git-tracked
    # (`cache: false`) outputs, which `dvc push --run-cache` does not carry (oodrl suite run
    # does): metrics, tier_metrics and render (SPEC §21), and the impact records (SPEC §23).
    second = tmp_path / "second"
    run(tmp_path, "git", "clone", "-q", str(repo), str(second))
    run(second, "git", "-c", "advice.detachedHead=false", "checkout", "-q", "HEAD~1")
    configure(second / PROJECT, remote)
    done = run(second / PROJECT, "dvc", "repro", "--pull", env=code_env(second))
    uncached = {"metrics", "tier_metrics", "render", "impact_reference", "impact@stuck_actuator"}
    assert set(ran_stages(done.stdout)) <= {"check_params", "train_policy", *uncached}
    assert len(built_ran) > 10 and done.stdout.count("is cached - skipping run") >= 10
    project_locks = {k: v for k, v in locks(repo).items() if k.startswith(PROJECT)}
    assert {k: v for k, v in locks(second).items() if k.startswith(PROJECT)} == project_locks


def test_suite_run_stops_in_one_line_when_the_bucket_does_not_exist(repo_root, s3_server, tmp_path):
    repo = two_environment_suite(repo_root, head_commit(repo_root), tmp_path / "repo")
    configure(repo, {"url": "s3://no-such-bucket/oodrl", "endpointurl": s3_server})
    before = checkout(repo)
    result = CliRunner().invoke(app, ["suite", "run", "--root", str(repo), "--workers", "2"])
    assert result.exit_code == 1
    assert_checking_line_then_the_error(result.output)
    # Not a refusal (which would make the remote read-only, tests/test_readonly_remote.py)
    assert "DVC remote 'lab' (s3://no-such-bucket/oodrl) fails a probe write" in result.output
    assert "bucket does not exist" in result.output
    assert checkout(repo) == before
