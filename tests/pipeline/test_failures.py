"""Failure behaviour of the pipeline: plugins, a failing detector, killed stages, corruption."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest
import yaml
from conftest import INJECTORS, detector_stages

from oodrl.io.layout import detector_stage
from oodrl.testing.pipeline import edit_params, environment, repro, run

pytestmark = pytest.mark.slow


def _add_detector(name: str, block: dict):
    def edit(params):
        params["benchmark"]["detectors"].append(name)
        params["detectors"][name] = block

    return edit


def test_module_class_detector_is_fitted_scored_and_reported(repo, plugin_env):
    edit_params(repo, _add_detector("speed", {"class": "oodrl_test_plugin:SpeedDetector"}))
    # Its stages are not in the pipeline yet: repro stops, naming the plugin and the fix.
    done = run(repo, "dvc", "repro", check=False, env=plugin_env)
    assert done.returncode != 0
    assert "oodrl_test_plugin.py" in done.stderr and "oodrl pipeline write" in done.stderr
    run(repo, "oodrl", "pipeline", "write", env=plugin_env)
    ran = repro(repo, env=plugin_env)
    assert {*detector_stages("speed"), "metrics", "render"} <= set(ran)
    results = yaml.safe_load((repo / "reports/results.yaml").read_text())
    speed = [r for r in results["records"] if r["detector"] == "speed" and r["kind"] == "anomaly"]
    assert sorted(r["injector"] for r in speed) == sorted(INJECTORS)
    assert "speed" in (repo / "reports/tables.md").read_text()


def test_failing_detector_names_itself_and_the_episode_and_keep_going_completes(repo, plugin_env):
    block = {"class": "oodrl_test_plugin:ExplodingDetector", "explode_on_seed": 10001}
    edit_params(repo, _add_detector("exploding", block))
    # Another branch has work to do too: with -k it completes despite the failing detector.
    edit_params(repo, lambda p: p["detectors"]["kde_density"].update(threshold_percentile=97.0))
    run(repo, "oodrl", "pipeline", "write", env=plugin_env)
    # The failing stage's own words are what a plain `dvc repro` stopped on: read here from the
    # -k run (a plain repro before it ran check_params and exploding's fit and score_clean for
    # them alone, and failed the same way).
    kept = run(repo, "dvc", "repro", "-k", check=False, env=plugin_env)
    assert kept.returncode != 0
    output = kept.stdout + kept.stderr
    assert "Detector 'exploding' failed scoring episode 1 (seed 10001)" in output
    assert "Traceback" not in output
    stage = detector_stage("kde_density", "score")
    assert f"Running stage '{stage}'" in kept.stdout
    status = run(repo, "dvc", "status", "--json", "--with-deps", "dvc.yaml").stdout
    status = yaml.safe_load(status) or {}
    pending = {name for name in status if name not in ("metrics", "render", "tier_metrics")}
    assert pending and all("exploding" in name for name in pending), sorted(pending)


def test_killed_stage_leaves_no_half_written_output_and_next_repro_completes(repo):
    """Kill collect_id while it writes its store: no store at the output path, then repro."""
    params = (repo / "params.yaml").read_text()
    edit_params(repo, lambda p: p["data"].update(n_id=64))  # long enough to be caught writing
    store = repo / "data" / "id.zarr"
    store.unlink()  # as DVC does before it runs a stage
    process = subprocess.Popen(
        [sys.executable, "-m", "oodrl", "collect-id", "--policy", "models/policy.pt",
         "--out", "data/id.zarr"],
        cwd=repo, env=environment(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    while process.poll() is None and not list(store.parent.glob(".id.zarr.tmp-*")):
        time.sleep(0.0005)
    process.send_signal(signal.SIGKILL)
    process.wait()
    if process.returncode == 0:
        pytest.skip("the stage finished before it could be killed mid-write")
    assert not store.exists(), "a killed stage must not leave a store at its output path"
    # The params as built, and the killed stage run again (forced: unforced, DVC would restore
    # the store from its cache): 4 episodes and no stage after it, instead of the 64 episodes
    # and every stage downstream of them. Its store comes out as the lock has it.
    (repo / "params.yaml").write_text(params)
    assert repro(repo, "-f", "-s", "collect_id") == ["collect_id"]
    assert run(repo, "dvc", "status", "-q", "--with-deps", "dvc.yaml", check=False).returncode == 0
    assert not list(store.parent.glob(".id.zarr.tmp-*"))


def test_corrupt_store_and_pickle_give_clear_errors(repo):
    store = repo / "data/eval.zarr"
    store.write_bytes(store.read_bytes()[: store.stat().st_size // 2])
    done = run(repo, "oodrl", "score", "kde_density", "--model",
               "models/detectors/kde_density.pkl", "--id", "data/id.zarr", "--eval",
               "data/eval.zarr", "--scores", "x", check=False)  # fmt: skip
    assert done.returncode == 1
    # The committed bytes are restored from the cache first, never recomputed (SPEC §22).
    assert "`dvc checkout --force data/eval.zarr`" in done.stderr
    assert done.stderr.index("dvc checkout") < done.stderr.index("dvc repro -s -f collect_eval")
    assert done.stderr.count("\n") == 1

    (repo / "models/detectors/kde_density.pkl").write_bytes(b"not a pickle")
    done = run(repo, "oodrl", "score", "kde_density", "--model",
               "models/detectors/kde_density.pkl", "--id", "data/id.zarr", "--eval",
               "data/id.zarr", "--scores", "x", check=False)  # fmt: skip
    assert done.returncode == 1
    hint = f"dvc repro -s -f {detector_stage('kde_density', 'fit')}"
    assert hint in done.stderr and "Traceback" not in done.stderr
