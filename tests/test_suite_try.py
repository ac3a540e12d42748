"""`oodrl suite try NAME --class module:Class` (SPEC §21): a detector checked against the
contract, added to the suite's params and run on every pipeline of a tiny suite (CartPole and
the leaderboard, real git and DVC), only its own stages and the results stages after them."""

from __future__ import annotations

import difflib
import json
from pathlib import Path

import pytest
import yaml
from suite_repo import (
    SUITE,
    code_env,
    copy_built,
    head_commit,
    run_folder,
    serial_built_suite,
    two_environment_suite,
)
from typer.testing import CliRunner

from oodrl.cli import app
from oodrl.errors import ConfigError
from oodrl.testing.pipeline import run

SUITE_PARAMS = "pipeline/params.yaml"
CARTPOLE = "pipeline/cartpole"

#: A class with a library's outlier API that scores every row alike: it fails the contract.
CONSTANT = """
import numpy as np


class Constant:
    def __init__(self, level=0.0):
        self.level = level

    def get_params(self, deep=True):
        return {"level": self.level}

    def set_params(self, **params):
        self.__dict__.update(params)
        return self

    def fit(self, X, y=None):
        return self

    def decision_function(self, X):
        return np.full(len(X), self.level)
"""


@pytest.fixture(scope="module")
def commit(repo_root) -> str:
    return head_commit(repo_root)


@pytest.fixture(scope="module")
def unbuilt_suite(repo_root, commit, tmp_path_factory) -> Path:
    """The tiny suite, not built: every refusal below must leave it as it is."""
    return two_environment_suite(repo_root, commit, tmp_path_factory.mktemp("unbuilt") / "repo")


def _tracked_and_params(repo: Path) -> dict[str, bytes]:
    """What a refused `suite try` may not touch: every file of the checkout outside git's and
    DVC's own directories."""
    return {
        path.relative_to(repo).as_posix(): path.read_bytes()
        for path in sorted(repo.rglob("*"))
        if path.is_file() and not {".git", ".dvc"} & set(path.relative_to(repo).parts)
    }


def _try(repo: Path, *args: str):
    return CliRunner().invoke(app, ["suite", "try", *args, "--root", str(repo)])


def test_a_class_failing_the_contract_is_one_line_and_adds_nothing(
    unbuilt_suite, tmp_path, monkeypatch
):
    (tmp_path / "constant_scores.py").write_text(CONSTANT)
    monkeypatch.chdir(tmp_path)  # a plugin module is looked up in the working directory
    before = _tracked_and_params(unbuilt_suite)
    result = _try(unbuilt_suite, "constant", "--class", "constant_scores:Constant")
    assert result.exit_code == 2, result.output
    progress, error = result.output.splitlines()
    assert progress.startswith("try: checking constant (constant_scores:Constant)")
    assert error == (
        "error: --class constant_scores:Constant: fails the detector contract of oodrl.testing "
        "(discrete actions): every step scored 0.0: the scores ignore the steps; 'constant' "
        "was not added."
    )
    assert _tracked_and_params(unbuilt_suite) == before


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (
            ["hbos", "--class", "pyod.models.nosuch:HBOS"],
            "Cannot import module 'pyod.models.nosuch'",
        ),
        (["hbos", "--class", "numpy:ndarray"], "numpy:ndarray has no outlier API"),
        (["hbos", "--class", "pyod.models.hbos"], "expected module:Class"),
        (["pyod_knn", "--class", "pyod.models.hbos:HBOS"], "'pyod_knn' is already a detector"),
        (["mahalanobis_distance", "--class", "pyod.models.hbos:HBOS"], "already a detector"),
        (["kde_density", "--class", "pyod.models.hbos:HBOS"], "already a detector"),
    ],
    ids=["no-module", "not-a-detector", "no-class", "a-block", "listed", "registered"],
)
def test_a_bad_class_or_a_taken_name_is_refused(unbuilt_suite, args, needle):
    before = _tracked_and_params(unbuilt_suite)
    result = _try(unbuilt_suite, *args)
    assert result.exit_code == 2, result.output
    error = result.output.splitlines()[-1]
    assert error.startswith("error: ") and needle in error, result.output
    assert "Traceback" not in result.output
    assert _tracked_and_params(unbuilt_suite) == before


@pytest.fixture(scope="module")
def built_suite(repo_root, commit, tmp_path_factory) -> Path:
    """The tiny suite built and committed, as a lab's checkout is after `oodrl suite run`: a
    copy of the serial build a test run makes once (suite_repo.serial_built_suite)."""
    built, _ = serial_built_suite(repo_root, commit, run_folder(tmp_path_factory))
    repo = copy_built(built, tmp_path_factory.mktemp("built") / "repo")
    run(repo, "git", "add", "-A")
    run(repo, "git", "commit", "-q", "-m", "the tiny suite, built")
    return repo


def _stale_stages(project: Path) -> set[str]:
    done = run(project, "dvc", "status", "--json")
    return set(json.loads(done.stdout))


@pytest.mark.slow
def test_try_runs_only_the_detectors_stages_and_prints_its_ranks(built_suite):
    lines: list[str] = []
    from oodrl.suite.try_detector import try_detector

    done = try_detector(
        built_suite, "hbos", "pyod.models.hbos:HBOS", "state", ["n_bins=10", "tol=0.5"],
        echo=lines.append,
    )  # fmt: skip
    # DVC ran the detector's stages and the results stages after them; the data, the policy
    # and the other detector's stages were restored from the cache, not run.
    ran = set(done.ran[CARTPOLE])
    assert ran == {
        "check_params",  # the suite's params changed: checked again, its stamp unchanged
        "detectors/hbos/dvc.yaml:fit",
        "detectors/hbos/dvc.yaml:score_clean",
        "detectors/hbos/dvc.yaml:score",
        "detectors/hbos/dvc.yaml:score_variants",
        "detectors/hbos/dvc.yaml:cells",
        "metrics",
        "tier_metrics",
    }, ran  # no collect, impact, train_policy or render stage, nothing of the other detector
    assert done.head_ran == (f"{SUITE}:leaderboard",)

    params = yaml.safe_load((built_suite / SUITE_PARAMS).read_text())
    assert params["benchmark"]["detectors"] == ["mahalanobis_distance", "hbos"]
    assert params["detectors"]["hbos"] == {
        "class": "pyod.models.hbos:HBOS", "features": "state", "n_bins": 10, "tol": 0.5,
    }  # fmt: skip
    assert (built_suite / CARTPOLE / "detectors" / "hbos" / "dvc.yaml").is_file()
    # Every stage but render (which streams every detector for its cost) is current.
    assert _stale_stages(built_suite / CARTPOLE) == {"render"}
    assert _stale_stages(built_suite / SUITE) == set()
    board = json.loads((built_suite / SUITE / "reports" / "leaderboard.json").read_text())
    assert "hbos" in board["detectors"]

    assert [rank.tier for rank in done.ranks] == board["tiers"]
    printed = [line for line in lines if line.startswith("  ")]
    assert len(printed) == len(board["tiers"])
    for line, rank in zip(printed, done.ranks, strict=True):
        assert f"hbos rank {rank.rank} of 2, " in line, line
        assert "| top 5: 1. " in line and "mahalanobis_distance" in line, line
    assert lines[-1].startswith("try: done in ")

    again = _try(built_suite, "hbos", "--class", "pyod.models.hbos:HBOS")
    assert again.exit_code == 2 and "'hbos' is already a detector" in again.output


@pytest.mark.slow
def test_a_task_restores_what_the_cache_holds_in_one_checkout(built_suite, tmp_path):
    """Without a remote, a task's fresh clone checks out what the shared cache holds before
    `dvc repro`: every current stage is then unchanged, where DVC would otherwise restore each
    one's outputs in turn ("is cached - skipping run"), rewriting dvc.lock after each (most of a
    try's run on the real suite: docs/performance.md)."""
    from oodrl.suite.run import ran_stages, restore_outputs

    clone = tmp_path / "clone"
    run(tmp_path, "git", "clone", "-q", str(built_suite), str(clone))
    project = clone / CARTPOLE
    cache = run(built_suite, "dvc", "cache", "dir").stdout.strip()
    run(project, "dvc", "cache", "dir", "--local", cache)
    restore_outputs(project, {}, None)
    done = run(project, "dvc", "repro", env=code_env(clone))
    assert ran_stages(done.stdout) == () and "is cached" not in done.stdout, done.stdout
    assert "didn't change" in done.stdout, done.stdout


def test_an_environment_listing_its_own_detectors_gets_the_new_one_appended(repo_root):
    """The SAC environments list the suite's detectors without the policy-view ones (a list in
    params replaces the one it extends): `suite try` appends the new detector there, and leaves
    a params file without a list of its own untouched."""
    from oodrl.suite.try_detector import add_to_own_list

    own = repo_root / "pipeline" / "hopper" / "params.yaml"
    text = add_to_own_list(own.read_text(), "my_detector")
    data = yaml.safe_load(text)
    before = yaml.safe_load(own.read_text())
    assert data["benchmark"]["detectors"] == [*before["benchmark"]["detectors"], "my_detector"]
    assert {k: v for k, v in data.items() if k != "benchmark"} == {
        k: v for k, v in before.items() if k != "benchmark"
    }  # nothing else changed, nulls included
    inherits = repo_root / "pipeline" / "hopper_policy1" / "params.yaml"  # extends hopper's
    assert add_to_own_list(inherits.read_text(), "my_detector") is None


def test_adding_a_detector_inserts_lines_and_changes_no_other(repo_root):
    """The suite's params keep every line as it was (flow-style blocks over several lines and
    their comments included): the new detector's list item and block are inserted lines."""
    from oodrl.suite.try_detector import add_to_params

    before = (repo_root / "pipeline" / "params.yaml").read_text()
    block = {"class": "pyod.models.hbos:HBOS", "features": "state", "n_bins": 10}
    after = add_to_params(before, "hbos", block, inherited=[])
    edits = difflib.SequenceMatcher(None, before.splitlines(), after.splitlines(), False)
    changes = [op for op in edits.get_opcodes() if op[0] != "equal"]
    assert [op[0] for op in changes] == ["insert", "insert"]  # no line removed or replaced
    added = [line for *_, j1, j2 in changes for line in after.splitlines()[j1:j2]]
    assert added == ["    - hbos", "  hbos:", '    class: "pyod.models.hbos:HBOS"',
                     "    features: state", "    n_bins: 10"]  # fmt: skip
    expected = yaml.safe_load(before)
    expected["benchmark"]["detectors"].append("hbos")
    expected["detectors"]["hbos"] = block
    assert yaml.safe_load(after) == expected


def test_a_flow_style_detector_list_is_refused_in_one_line():
    from oodrl.suite.try_detector import add_to_own_list

    with pytest.raises(ConfigError, match="empty or a flow-style list"):
        add_to_own_list("benchmark:\n  detectors: [a, b]\n", "x")
