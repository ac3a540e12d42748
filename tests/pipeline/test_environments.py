"""An environment's own pipeline (SPEC §12): pipeline/cartpole/dvc.yaml, generated from the
template, reads pipeline/cartpole/params.yaml, which extends the suite's pipeline/params.yaml
and through it the shared params.yaml. The
directory is a DVC project of its own (a subrepo sharing the root's cache): `dvc repro` runs
in it, and the root's DVC does not list its stages.

The pipeline is the test run's one serial build of the tiny suite (tests/suite_repo.py), whose
CartPole project `dvc repro` built in its directory, copied."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from suite_repo import (
    SUITE_DETECTORS,
    SUITE_INJECTORS,
    code_env,
    copy_built,
    head_commit,
    run_folder,
    serial_built_suite,
)

from oodrl.io.layout import detector_stage
from oodrl.io.store import read_trajectories
from oodrl.testing.pipeline import lock_hashes, repro, run

pytestmark = pytest.mark.slow

ENV = "pipeline/cartpole"


@pytest.fixture(scope="module")
def cartpole_repo(tmp_path_factory, repo_root) -> Path:
    made, _ = serial_built_suite(repo_root, head_commit(repo_root), run_folder(tmp_path_factory))
    return copy_built(made, tmp_path_factory.mktemp("env") / "repo")


def _ran(repo: Path) -> set[str]:
    """The stages that ran, named as in the root pipeline (e.g. `detectors/<d>/dvc.yaml:fit`)."""
    ran = repro(repo / ENV, env=code_env(repo))
    return {name.removeprefix("dvc.yaml:") for name in ran}


def test_environment_pipeline_builds_in_its_directory(cartpole_repo):
    env = cartpole_repo / ENV
    results = yaml.safe_load((env / "reports/results.yaml").read_text())
    anomaly = {(r["detector"], r["injector"]) for r in results["records"] if r["kind"] == "anomaly"}
    assert anomaly == {(d, i) for d in SUITE_DETECTORS for i in SUITE_INJECTORS}
    attrs = read_trajectories(env / "data/id.zarr", stage="collect_id").attrs
    assert (attrs["env_id"], attrs["T"]) == ("CartPole-v1", 60)
    assert _ran(cartpole_repo) == set()
    # Its outputs went to the root's cache: it has none of its own.
    digest = lock_hashes(env)["data/id.zarr"]
    assert (cartpole_repo / ".dvc" / "cache" / "files" / "md5" / digest[:2] / digest[2:]).is_file()
    assert not (env / ".dvc" / "cache").exists()
    # The root's DVC collects its own stages, never the subrepo's.
    root_stages = run(cartpole_repo, "dvc", "stage", "list", "--name-only").stdout.split()
    assert "collect_id" in root_stages and not any("cartpole" in s for s in root_stages)


def test_a_shared_detector_knob_reruns_that_detector_in_the_environment(cartpole_repo):
    params = yaml.safe_load((cartpole_repo / "params.yaml").read_text())
    (detector,) = SUITE_DETECTORS
    params["detectors"][detector]["threshold_percentile"] = 95.0
    (cartpole_repo / "params.yaml").write_text(yaml.safe_dump(params))
    # The stages read the knob from the params check_params merges: once it has run, `dvc
    # status` lists the stages that read it, the ones `dvc repro` runs next; its scoring stages
    # and render follow them in the graph, the root's (test_pipeline's detector knob test).
    ran = repro(cartpole_repo / ENV, "-s", "check_params", env=code_env(cartpole_repo))
    assert [name.removeprefix("dvc.yaml:") for name in ran] == ["check_params"]
    status = run(cartpole_repo / ENV, "dvc", "status", "--json").stdout
    assert {name.removeprefix("dvc.yaml:") for name in json.loads(status)} == {
        detector_stage(detector, "fit"), detector_stage(detector, "cells"), "metrics",
        "tier_metrics",
    }  # fmt: skip
