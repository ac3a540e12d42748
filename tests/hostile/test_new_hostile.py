"""`oodrl new` against hostile input (issue 37, SPEC §18 and §22).

An interrupted run leaves `pipeline/NAME` complete or absent, in a real git + DVC repository:
SIGTERM and SIGHUP leave no staging folder either, and the one a SIGKILLed run leaves is
removed by the next run;
and four inputs whose messages misled now get one accurate line: Gymnasium's `module:EnvId`,
a missing dataset directory, an image environment, a policy no better than random.
"""

from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from oodrl.cli import app
from oodrl.suite.new import new_pipeline
from oodrl.suite.pipeline import check_files, check_pipeline
from oodrl.testing.pipeline import environment, run

#: Two CartPole controllers given as `module:function` policies (no training, fast to run).
POLICIES = '''import numpy as np


def balance(observations):
    """Push toward where the pole falls: 500, the most CartPole gives."""
    return (observations[:, 2] + 0.5 * observations[:, 3] > 0).astype(np.int64)


def left(observations):
    """Always push left: the pole falls sooner than under random pushes."""
    return np.zeros(len(observations), np.int64)
'''
NEW = ["new", "cart", "--env", "CartPole-v1", "--policy", "cart_policies:balance"]
#: A stream of 30 steps and a 2-episode report: the run takes seconds.
TINY = ["--T", "30", "--episodes", "2"]


@pytest.fixture(scope="module")
def repo(tmp_path_factory, repo_root: Path) -> Path:
    """A small git + DVC project: the shared params, the package sources (linked: the DVC
    files' code deps), its generated root and suite pipelines, and the policies' module."""
    repo = tmp_path_factory.mktemp("new_hostile") / "repo"
    for name in ("params.yaml", ".gitignore", ".dvc/config", ".dvc/.gitignore"):
        (repo / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(repo_root / name, repo / name)
    (repo / "src").symlink_to(repo_root / "src")
    (repo / "cart_policies.py").write_text(POLICIES)
    run(repo, "oodrl", "pipeline", "write")
    run(repo, "git", "init", "-q")
    run(repo, "git", "add", "-A")
    run(repo, "git", "commit", "-q", "-m", "a small project")
    return repo


@pytest.fixture
def root(tmp_path: Path, repo_root: Path, monkeypatch) -> Path:
    """A project of the shared params and the package sources, for in-process runs."""
    (tmp_path / "params.yaml").write_text((repo_root / "params.yaml").read_text())
    (tmp_path / "src").symlink_to(repo_root / "src")
    (tmp_path / "cart_policies.py").write_text(POLICIES)
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


def oodrl(*args: str) -> list[str]:
    return [str(Path(sys.executable).with_name("oodrl")), *args]


def staging_folders(pipelines: Path) -> list[Path]:
    return sorted(pipelines.glob(".cart.new-*"))


def killed_at(repo: Path, signum: int, point: str | float) -> None:
    """`oodrl new` started, then sent `signum`: `point` seconds after the start (a float), or
    as soon as a new path matching the pattern `point` (under pipeline/) exists (not one a
    killed run left)."""
    pipelines = repo / "pipeline"
    left = set(pipelines.glob(point)) if isinstance(point, str) else set()
    process = subprocess.Popen(oodrl(*NEW, *TINY), cwd=repo, env=environment(),
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    if isinstance(point, float):
        time.sleep(point)
    else:
        while process.poll() is None and not set(pipelines.glob(point)) - left:
            time.sleep(0.001)
    if process.poll() is None:
        process.send_signal(signum)
    process.wait(timeout=120)


def assert_complete_or_absent(repo: Path, at: str, staging_left: bool = False) -> None:
    """pipeline/cart complete (its DVC files current) or absent, no staging folder (unless a
    SIGKILL may have left one), and git sees nothing else; then removed, so the next run
    makes it again."""
    made = repo / "pipeline" / "cart"
    if not staging_left:
        assert staging_folders(repo / "pipeline") == [], at
    status = run(repo, "git", "status", "--porcelain").stdout.splitlines()
    made_now = ["?? pipeline/cart/"] if made.exists() else []
    staged = [f"?? pipeline/{p.name}/" for p in staging_folders(repo / "pipeline")]
    assert sorted(status) == sorted(made_now + staged), (at, status)
    if made.exists():
        check_pipeline(made / "dvc.yaml")  # raises unless every DVC file is what it must be
        shutil.rmtree(made)


def test_an_interrupted_new_leaves_the_pipeline_complete_or_absent(repo: Path):
    late = random.Random(37).uniform(3.0, 6.0)  # the run takes about 4 s
    kills = [  # each point costs a run, so the signals share them out
        (signal.SIGHUP, 0.3),  # before the staging folder: importing
        (signal.SIGTERM, ".cart.new-*"),  # the staging folder made
        # SIGKILL cleans up nothing: the pipeline must still be complete or absent (one rename
        # makes it), and the dead run's staging folder must not block the next run.
        (signal.SIGKILL, ".cart.new-*/dvc.yaml"),
        (signal.SIGHUP, ".cart.new-*/models/policy.pt"),
        (signal.SIGKILL, "cart"),  # the moment the pipeline appears: it has its dvc.yaml
        (signal.SIGTERM, late),
    ]
    for signum, point in kills:
        killed_at(repo, signum, point)
        assert_complete_or_absent(repo, f"{signum!r} at {point}", signum == signal.SIGKILL)
    done = subprocess.run(oodrl(*NEW, *TINY), cwd=repo, env=environment(), capture_output=True,
                          text=True, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    # Only the generated files: the copy's tiny params leave its locks stale by design.
    check_files(repo)
    assert_complete_or_absent(repo, "no signal")


#: `oodrl new` called from Python; argv: the signal it sends itself, the function
#: (module.function) after which it does, the project root.
INTERRUPTED = """
import importlib, os, signal, sys
from pathlib import Path

from oodrl.suite.new import new_pipeline

signum, where, root = int(sys.argv[1]), sys.argv[2], Path(sys.argv[3])
module_name, _, function = where.rpartition(".")
module = importlib.import_module(module_name)
original = getattr(module, function)


def interrupted(*args, **kwargs):
    done = original(*args, **kwargs)
    os.kill(os.getpid(), signum)  # its handler runs before the next line
    return done


setattr(module, function, interrupted)
sys.path.insert(0, str(root))
try:
    new_pipeline(root, "cart", "CartPole-v1", policy="cart_policies:balance", T=30, episodes=2)
finally:
    assert signal.getsignal(signum) == signal.SIG_DFL, "the default handler is back"
"""


@pytest.mark.parametrize(
    ("signum", "where"),
    [
        (signal.SIGTERM, "oodrl.suite.pipeline.subrepo_files"),
        (signal.SIGHUP, "oodrl.suite.new._check"),
    ],
    ids=["SIGTERM-writing-dvc-files", "SIGHUP-checking-params"],
)
def test_a_signal_while_it_writes_removes_the_staging_folder(root, signum, where):
    """Called from Python with the default handlers (in a process of its own: a signal not
    handled would end pytest): the signal unwinds, exit code 128 + signal, nothing left."""
    done = subprocess.run([sys.executable, "-c", INTERRUPTED, str(int(signum)), where, str(root)],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert done.returncode == 128 + signum, done.stderr
    assert list((root / "pipeline").iterdir()) == []


class Stopped(Exception):
    """Raised by `stop`: a caller's own SIGTERM handler, as oodrl's CLI has one."""


def stop(number, frame):
    raise Stopped(number)


def new_pipeline_stopped(root: Path):
    """`oodrl new` called with `stop` as SIGTERM's handler, stopped by the SIGTERM a patched
    function sends; the handler in place right after (the previous one restored in any case)."""
    kept = signal.signal(signal.SIGTERM, stop)
    try:
        with pytest.raises(Stopped):
            new_pipeline(root, "cart", "CartPole-v1", policy="cart_policies:balance", T=30,
                         episodes=2)  # fmt: skip
        return signal.getsignal(signal.SIGTERM)
    finally:
        signal.signal(signal.SIGTERM, kept)


def test_a_callers_own_signal_handler_is_kept_and_cleans_up_too(root, monkeypatch):
    """oodrl's CLI turns SIGTERM into KeyboardInterrupt: the staging folder goes just the same,
    and the caller's handler is in place after."""
    import oodrl.suite.pipeline

    def interrupted(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(oodrl.suite.pipeline, "subrepo_files", interrupted)
    assert new_pipeline_stopped(root) is stop
    assert list((root / "pipeline").iterdir()) == []


def test_a_signal_the_moment_the_staging_folder_is_made_removes_it(root, monkeypatch):
    """The signal handled as `mkdir` returns (CI's SIGTERM at `.cart.new-*` once met it there,
    before the cleanup's try): the folder goes all the same."""
    import pathlib

    made = pathlib.Path.mkdir

    def mkdir_then_signalled(self, *args, **kwargs):
        made(self, *args, **kwargs)
        if self.name.startswith(".cart.new-"):
            os.kill(os.getpid(), signal.SIGTERM)  # its handler runs before this returns

    monkeypatch.setattr(pathlib.Path, "mkdir", mkdir_then_signalled)
    new_pipeline_stopped(root)
    assert list((root / "pipeline").iterdir()) == []


def test_a_dead_runs_staging_folder_never_blocks_the_next(root):
    pipelines = root / "pipeline"
    exited = subprocess.Popen(["true"])
    exited.wait()  # reaped: its pid names no process (a SIGKILLed `oodrl new`, say)
    dead = pipelines / f".cart.new-{exited.pid}"
    live = pipelines / f".other.new-{os.getppid()}"  # another `oodrl new`, still running
    for folder in (dead, live):
        (folder / "models").mkdir(parents=True)
        (folder / "params.yaml").write_text("half written\n")
    made = new_pipeline(root, "cart", "CartPole-v1", policy="cart_policies:balance", T=30,
                        episodes=2)  # fmt: skip
    assert (made.directory / "dvc.yaml").is_file()
    assert {p.name for p in pipelines.iterdir()} == {"cart", live.name}


# -- messages that misled: one accurate line each ------------------------------------------------
def new(root: Path, *arguments: str):
    result = CliRunner().invoke(app, ["new", "x", *arguments, "--root", str(root)])
    assert result.output.startswith("error: ") and result.output.count("\n") == 1, result.output
    assert not (root / "pipeline").exists() or not any((root / "pipeline").iterdir())
    return result


def test_gymnasium_module_env_id_syntax_is_refused_saying_what_is_allowed(root):
    result = new(root, "--env", "my_envs:MyEnv-v0", "--train", "ppo", "--steps", "1")
    assert result.exit_code == 2
    assert "Gymnasium's module:EnvId form" in result.output
    assert "give an id that `import gymnasium` registers" in result.output


@pytest.mark.parametrize("dataset", ["./missing", "~/no/such/oodrl-dataset", "recordings/x"])
def test_a_missing_dataset_directory_is_named_as_such(root, monkeypatch, dataset):
    monkeypatch.chdir(root)
    (root / "recordings").mkdir()  # recordings/x: a path, as recordings/ is a directory here
    result = new(root, "--dataset", dataset)
    assert result.exit_code == 2
    assert f"--dataset: no such dataset directory: {dataset}" in result.output
    assert "minari" not in result.output


def test_a_directory_that_holds_no_dataset_is_named_as_such(root):
    (root / "empty").mkdir()
    result = new(root, "--dataset", str(root / "empty"))
    assert result.exit_code == 2
    assert "is not a Minari dataset's directory (no metadata.json" in result.output
    assert "minari download" not in result.output


def test_a_dataset_id_that_is_not_local_gets_the_download_hint(root, monkeypatch, tmp_path):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "datasets"))
    result = new(root, "--dataset", "mujoco/hopper/missing-v0")
    assert result.exit_code == 2
    assert "`minari download mujoco/hopper/missing-v0`" in result.output


@pytest.mark.parametrize("flatten", [[], ["--flatten"]], ids=["plain", "flatten"])
def test_an_image_environment_is_refused_without_suggesting_flatten(root, flatten):
    result = new(root, "--env", "CarRacing-v3", *flatten, "--train", "ppo", "--steps", "1")
    assert result.exit_code == 2
    assert "observes images" in result.output and "need a feature extractor" in result.output
    assert "--flatten" not in result.output


def test_a_policy_no_better_than_random_is_refused(root):
    result = new(root, "--env", "CartPole-v1", "--policy", "cart_policies:left", *TINY)
    assert result.exit_code == 1
    assert "not above a uniformly random policy's" in result.output
    assert "train it longer" in result.output


def test_a_dqn_trained_too_briefly_is_refused(root):
    """A few hundred steps: DQN's Q-network is still its initial one, greedy on one action."""
    result = new(root, "--env", "CartPole-v1", "--train", "dqn", "--steps", "300", *TINY)
    assert result.exit_code == 1
    assert "not above a uniformly random policy's" in result.output
    assert "train longer (--steps, now 300)" in result.output
