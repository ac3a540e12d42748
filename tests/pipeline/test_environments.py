"""An environment's own pipeline (SPEC §12): pipeline/cartpole/dvc.yaml, generated from the
template, reads pipeline/cartpole/params.yaml, which extends the suite's pipeline/params.yaml
and through it the shared params.yaml. The
directory is a DVC project of its own (a subrepo sharing the root's cache): `dvc repro` runs
in it, and the root's `dvc status` does not list its stages."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from conftest import DETECTORS, INJECTORS, tiny_params
from suite_repo import root_detectors_only

from oodrl.io.layout import detector_stage
from oodrl.io.store import read_trajectories
from oodrl.testing.pipeline import copy_project, repro, run

pytestmark = pytest.mark.slow

ENV = "pipeline/cartpole"


@pytest.fixture(scope="module")
def cartpole_repo(tmp_path_factory, repo_root, _default_params) -> Path:
    if not (repo_root / ENV / "models" / "policy.pt").is_file():
        pytest.skip(f"{ENV}/models/policy.pt is not there yet")
    repo = copy_project(repo_root, tmp_path_factory.mktemp("env") / "repo")
    (repo / "params.yaml").write_text(yaml.safe_dump(tiny_params(_default_params)))
    suite = yaml.safe_load((repo / "pipeline" / "params.yaml").read_text())
    root_detectors_only(suite)
    (repo / "pipeline" / "params.yaml").write_text(yaml.safe_dump(suite, sort_keys=False))
    local = yaml.safe_load((repo / ENV / "params.yaml").read_text())
    local["env"] = {**local.get("env", {}), "T": 60, "onset": None}
    (repo / ENV / "params.yaml").write_text(yaml.safe_dump(local, sort_keys=False))
    run(repo, "oodrl", "pipeline", "write")
    run(repo, "git", "add", "-A")
    run(repo, "git", "commit", "-q", "-m", "tiny params")
    repro(repo / ENV)
    return repo


def _ran(repo: Path) -> set[str]:
    """The stages that ran, named as in the root pipeline (e.g. `detectors/<d>/dvc.yaml:fit`)."""
    ran = repro(repo / ENV)
    return {name.removeprefix("dvc.yaml:") for name in ran}


def test_environment_pipeline_builds_in_its_directory(cartpole_repo):
    env = cartpole_repo / ENV
    results = yaml.safe_load((env / "reports/results.yaml").read_text())
    anomaly = {(r["detector"], r["injector"]) for r in results["records"] if r["kind"] == "anomaly"}
    assert anomaly == {(d, i) for d in DETECTORS for i in INJECTORS}
    attrs = read_trajectories(env / "data/id.zarr", stage="collect_id").attrs
    assert (attrs["env_id"], attrs["T"]) == ("CartPole-v1", 60)
    assert (env / "dvc.lock").is_file() and not (cartpole_repo / "data" / "id.zarr").exists()
    assert _ran(cartpole_repo) == set()
    # Its outputs went to the root's cache, and the root's status ignores it (never built there).
    assert any((cartpole_repo / ".dvc" / "cache" / "files" / "md5").iterdir())
    assert not (env / ".dvc" / "cache").exists()
    root_status = run(cartpole_repo, "dvc", "status", "--json").stdout
    assert "cartpole" not in root_status and "collect_id" in root_status


def test_a_shared_detector_knob_reruns_that_detector_in_the_environment(cartpole_repo):
    params = yaml.safe_load((cartpole_repo / "params.yaml").read_text())
    params["detectors"]["kde_density"]["threshold_percentile"] = 95.0
    (cartpole_repo / "params.yaml").write_text(yaml.safe_dump(params))
    # The stages read the knob from the params check_params merges: once it has run, `dvc
    # status` lists the stages that read it, the ones `dvc repro` runs next; its scoring stages
    # and render follow them in the graph, the root's (test_pipeline's detector knob test).
    ran = repro(cartpole_repo / ENV, "-s", "check_params")
    assert [name.removeprefix("dvc.yaml:") for name in ran] == ["check_params"]
    status = run(cartpole_repo / ENV, "dvc", "status", "--json").stdout
    assert {name.removeprefix("dvc.yaml:") for name in json.loads(status)} == {
        detector_stage("kde_density", "fit"), detector_stage("kde_density", "cells"), "metrics",
        "tier_metrics",
    }  # fmt: skip
