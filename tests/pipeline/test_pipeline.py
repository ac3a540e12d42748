"""The real DVC pipeline on tiny params, in a throw-away git + DVC repository."""

from __future__ import annotations

import json

import pytest
import yaml
from conftest import (
    DETECTORS,
    INJECTORS,
    detector_stages,
    fault_scoring,
    injector_stages,
)

from oodrl.io.layout import detector_pipeline, detector_stage
from oodrl.testing.pipeline import TINY_TIERS, edit_params, lock_hashes, repro, run

pytestmark = pytest.mark.slow


def test_full_pipeline_writes_every_output(built_repo):
    for path in [
        "data/id.zarr", "data/eval.zarr", "data/ood/stuck_actuator.zarr",
        "data/sweep/observation_delay.zarr", "models/detectors/kde_density.pkl",
        "scores/kde_density/eval.zarr", "scores/kde_density/stuck_actuator.zarr",
        "scores/kde_density/sweep/stuck_actuator.zarr",
        "reports/results.yaml", "reports/sweep_results.yaml", "reports/metrics.json",
        "reports/tables.md", "reports/run_meta.yaml", "reports/headline.md",
        "reports/figures/matched_auroc_heatmap.png", "reports/figures/severity_curves.png",
        "reports/figures/score_traces.png",
    ]:  # fmt: skip
        assert (built_repo / path).exists(), path
    results = yaml.safe_load((built_repo / "reports/results.yaml").read_text())
    anomaly = [r for r in results["records"] if r["kind"] == "anomaly"]
    assert {(r["detector"], r["injector"]) for r in anomaly} == {
        (d, i) for d in DETECTORS for i in INJECTORS
    }
    for record in anomaly:
        assert set(record["metrics"]["matched_auroc"]) == {
            "mean", "std", "ci_low", "ci_high", "n_episodes"
        }  # fmt: skip
        assert record["metrics"]["matched_auroc"]["n_episodes"] == 3
    nulls = {(r["detector"], r["mode"]) for r in results["records"] if r["kind"] == "null"}
    assert nulls == {(d, m) for d in DETECTORS for m in ("online", "posthoc")}
    _check_tier_results(built_repo)
    cost = yaml.safe_load((built_repo / "reports/run_meta.yaml").read_text())["cost"]
    assert sorted(cost) == sorted(DETECTORS)  # SPEC §13: cost beside accuracy, per detector
    for detector, entry in cost.items():
        pickle = built_repo / "models" / "detectors" / f"{detector}.pkl"
        assert entry["fit_s"] > 0, detector  # recorded by the fit stage
        assert entry["fitted_bytes"] == pickle.stat().st_size
        assert entry["step_us_p99"] >= entry["step_us_median"] > 0


def _check_tier_results(repo) -> None:
    """SPEC §15: every detector at every reachable tier of every fault, at the per-stream rule."""
    from oodrl.metrics.stamp import PROTOCOL_VERSION
    from oodrl.metrics.tier_results import TIER_RESULTS, load_tier_results, tier_results_text
    from oodrl.protocol.impact import tier_severity
    from oodrl.protocol.tiers import read_impact, read_tiers

    document = load_tier_results(repo / TIER_RESULTS)
    assert (repo / TIER_RESULTS).read_text() == tier_results_text(document)  # canonical text
    assert document["protocol_version"] == PROTOCOL_VERSION
    assert document["params_hash"].startswith("sha256:")
    reachable = {
        (i, tier) for i in INJECTORS for tier in read_tiers(repo / f"data/impact/{i}.yaml", i)[0]
    }
    records = document["records"]
    assert {(r["detector"], r["injector"], r["tier"]) for r in records} == {
        (d, i, t) for d in DETECTORS for (i, t) in reachable
    }
    n_streams, n_audit = TINY_TIERS["n_streams"], TINY_TIERS["n_audit"]
    for record in records:
        point = record["operating_point"]
        # Cells of n_streams faulty streams; the false-alarm rate from the audit streams.
        assert point["alpha"] == 0.05 and point["n_clean"] == n_audit
        assert point["n_faulty"] == n_streams and isinstance(record["verified"], bool)
        detections = record["episodes"]["detection_rate@100"]
        assert len(detections) == n_streams and set(detections) <= {0.0, 1.0}
        assert sum(detections) / n_streams == pytest.approx(point["detection_rate"], abs=1e-6)
        audit = document["false_alarm_audit"][record["detector"]]
        assert audit["n_streams"] == n_audit and audit["rate"] == point["clean_false_alarm_rate"]
    for fault, impact in document["impact"].items():
        assert set(impact["tiers"]) == {"benign", "mild", "moderate", "severe"}, fault
        measured = read_impact(repo / f"data/impact/{fault}.yaml", fault)["fault"]
        assert impact["curve"] == measured["curve"]  # the leaderboard page draws it
        for tier in impact["tiers"].values():
            assert tier_severity(tier) is None or 0 < tier["severity"] <= 1
            if tier_severity(tier) is not None:  # measured where it is read, and verified
                batch = TINY_TIERS["search"]["verify_batch"]
                assert tier["verification"]["episodes"] == batch * tier["verification"]["batches"]
    assert set(document["minimum_detectable_impact"]) <= set(DETECTORS)
    assert (repo / "reports/tiers/tables.md").read_text().startswith("# Impact tiers")
    assert (repo / "reports/tiers/impact_curves.png").stat().st_size > 0


def test_up_to_date_after_repro(repo):
    # The root pipeline's stages (the environments' pipelines are not built in the copy).
    assert run(repo, "dvc", "status", "-q", "--with-deps", "dvc.yaml", check=False).returncode == 0
    assert repro(repo) == []


def test_injector_param_reruns_only_that_injector(repo):
    before = lock_hashes(repo)
    edit_params(repo, lambda p: p["anomaly"]["injectors"]["observation_delay"].update(max_delay=4))
    status = run(repo, "dvc", "status", "--json", "dvc.yaml").stdout
    # The metrics stages stamp their results with the hash of every params section they read.
    stale = sorted(json.loads(status))
    assert stale == sorted(
        ["check_params", *injector_stages("observation_delay"), "metrics", "tier_metrics"]
    )
    # What `dvc repro` runs: the stale stages and what follows them in the graph (the detector
    # knob's test does the same): a repro of them all took 29 s on a loaded machine, this 5 s.
    ran = {*stale, *_downstream(repo, set(stale) - {"check_params"})}
    assert sorted(ran) == sorted([
        "check_params", *injector_stages("observation_delay"),
        *fault_scoring(DETECTORS), "metrics", "render", "tier_metrics",
    ])  # fmt: skip
    # The knob changes that injector's headline set (so what follows it runs), not the other's.
    assert repro(repo, "-s", "collect_ood@observation_delay") == ["collect_ood@observation_delay"]
    after = lock_hashes(repo)
    assert after["data/ood/stuck_actuator.zarr"] == before["data/ood/stuck_actuator.zarr"]
    assert after["data/ood/observation_delay.zarr"] != before["data/ood/observation_delay.zarr"]


def _stale(repo, *after: str) -> list[str]:
    """The stages `dvc repro` starts with, `after` the given ones ran: those `dvc status` lists
    (DVC then runs the stages downstream of one whose outputs changed: `_downstream`)."""
    for stage in after:
        assert repro(repo, "-s", stage) == [stage]
    return sorted([*after, *json.loads(run(repo, "dvc", "status", "--json").stdout)])


def _downstream(repo, stages) -> set[str]:
    """The stages that follow `stages` in the pipeline's graph: a dep of theirs is an output of
    one of `stages`, or holds or is held by one (deps and outs as the locks record them; a lock
    keeps the stages of injectors the tiny benchmark dropped, and protocol 3's per-injector
    scoring stages, left out here)."""
    locks = {"": repo / "dvc.lock"}
    locks.update({f"{detector_pipeline(d)}:": repo / detector_pipeline(d) for d in DETECTORS})
    locked = {
        prefix + name: stage
        for prefix, path in locks.items()
        for name, stage in yaml.safe_load(path.with_suffix(".lock").read_text())["stages"].items()
        if name.partition("@")[2] in ("", *INJECTORS) and not (prefix and "@" in name)
    }

    def follows(dep: str, out: str) -> bool:
        return dep == out or dep.startswith(f"{out}/") or out.startswith(f"{dep}/")

    found, pending = set(), list(stages)
    while pending:
        outs = [out["path"] for out in locked[pending.pop()].get("outs", [])]
        for name, stage in locked.items():
            deps = [dep["path"] for dep in stage.get("deps", [])]
            if name not in found and any(follows(d, o) for d in deps for o in outs):
                found.add(name)
                pending.append(name)
    return found


def test_detector_param_reruns_only_that_detector(repo):
    edit_params(repo, lambda p: p["detectors"]["kde_density"].update(threshold_percentile=95.0))
    stale = _stale(repo)  # the knob's readers: fit, cells (its latency), the results' stamps
    assert stale == sorted(["check_params", detector_stage("kde_density", "fit"),
                            detector_stage("kde_density", "cells"), "metrics",
                            "tier_metrics"])  # fmt: skip
    # What follows them (check_params's outputs stay the same when a check passes).
    ran = {*stale, *_downstream(repo, set(stale) - {"check_params"})}
    assert sorted(ran) == sorted([
        "check_params", *detector_stages("kde_density"), "metrics", "render", "tier_metrics",
    ])  # fmt: skip


def test_headline_severity_experiment_reruns_the_headline_sets_and_their_scoring_only(repo):
    """`dvc exp run -S anomaly.severity=…` runs what a `dvc repro` after that edit would (one
    run checks both: the stages it runs, and `dvc metrics diff` against the committed run; a
    repro and an experiment of such an edit took 50 s on a loaded machine, this 31 s)."""
    run(repo, "git", "add", "-A")
    run(repo, "git", "commit", "-q", "-m", "baseline run")
    before = lock_hashes(repo)
    done = run(repo, "dvc", "exp", "run", "-S", "anomaly.severity=0.7")
    ran = sorted(
        line.split("'")[1]
        for line in (done.stdout + done.stderr).splitlines()
        if line.startswith("Running stage '")
    )
    after = lock_hashes(repo)  # the experiment's results and locks stay in the workspace
    # The sweeps and tier streams are scored by a stage of their own (SPEC §23): not re-run.
    for d in DETECTORS:
        for i in INJECTORS:
            for store in (f"scores/{d}/sweep/{i}.zarr", f"scores/{d}/tiers/{i}.zarr"):
                assert after[store] == before[store], store
            assert after[f"scores/{d}/{i}.zarr"] != before[f"scores/{d}/{i}.zarr"]
    assert ran == sorted([
        "check_params", *(f"collect_ood@{i}" for i in INJECTORS),
        *(detector_stage(d, stage) for d in DETECTORS for stage in ("score", "cells")),
        "metrics", "render", "tier_metrics",
    ])  # fmt: skip
    diff = run(repo, "dvc", "metrics", "diff", "--json").stdout
    changes = json.loads(diff)["reports/metrics.json"]
    assert any(v["diff"] not in (0, None) for v in changes.values()), changes


def _append_comment(repo, path: str) -> None:
    with (repo / path).open("a") as source:
        source.write("\n# an edit\n")


CODE_EDITS = {  # edited file -> the stages allowed to run (DVC skips those whose inputs held)
    "src/oodrl/detectors/kde.py": {
        "check_params", *detector_stages("kde_density"), "metrics", "render", "tier_metrics",
    },
    "src/oodrl/injectors/posthoc.py": {  # observation_delay is the tiny params' post-hoc one
        "check_params", *injector_stages("observation_delay"),
        *fault_scoring(DETECTORS), "metrics", "render", "tier_metrics",
        # The tier stages of every fault, and the impact reference, import the live observation
        # faults (an over-approximation: their outputs, and so what follows them, stay the same).
        "impact_reference", "impact@stuck_actuator", "collect_tiers@stuck_actuator",
    },
    "src/oodrl/metrics/ranking.py": {  # the cells import it with the records they compute
        "check_params", *(detector_stage(d, "cells") for d in DETECTORS), "metrics", "render",
        "tier_metrics",
    },
}  # fmt: skip
MUST_RUN = {  # the stages whose code stamp changed: they run even when outputs stay the same
    "src/oodrl/detectors/kde.py": {
        "check_params",
        detector_stage("kde_density", "fit"),
        detector_stage("kde_density", "score_clean"),
    },
    "src/oodrl/injectors/posthoc.py": {"collect_ood@observation_delay"},
    "src/oodrl/metrics/ranking.py": {"metrics"},
}


# check_params writes the code stamps: after it, `dvc status` lists the stages whose stamp
# changed, the ones `dvc repro` runs (a comment changes no stage's outputs, so no stage that
# follows them runs).
@pytest.mark.parametrize("path", list(CODE_EDITS))
def test_code_edit_reruns_exactly_the_stages_that_execute_it(repo, path):
    _append_comment(repo, path)
    stale = set(_stale(repo, "check_params"))
    assert MUST_RUN[path] <= stale <= CODE_EDITS[path], sorted(stale)


def test_code_edit_in_a_shared_module_reruns_every_stage_that_executes_it(repo):
    """BaseDetector.score runs in every scoring stage, through the pickle."""
    _append_comment(repo, "src/oodrl/core/detector.py")
    stale = set(_stale(repo, "check_params"))
    assert {stage for d in DETECTORS for stage in detector_stages(d)} <= stale


def test_lock_stays_small(built_repo):
    """One stamp per stage instead of the files of its closure (SPEC §12)."""
    lock = yaml.safe_load((built_repo / "dvc.lock").read_text())["stages"]
    detector_file = built_repo / detector_pipeline(DETECTORS[0])
    detector_lock = yaml.safe_load(detector_file.with_suffix(".lock").read_text())["stages"]
    assert len(lock["collect_id"]["deps"]) <= 6
    # The reports it draws, the evaluation set, and each detector's model and the stores it
    # plots (its clean and headline scores): files, never a directory (SPEC §23).
    n = len(INJECTORS)
    assert len(lock["render"]["deps"]) == 5 + len(DETECTORS) * (n + 2)
    # The checked params and its code stamp, then what it reads: score_clean the model and the
    # five clean sets; cells every score store of the detector and each fault's impact record.
    deps = {"fit": 3, "score_clean": 8, "score": 3 + n, "score_variants": 3 + 2 * n,
            "cells": 7 + 4 * n}  # fmt: skip
    assert {name: len(detector_lock[name]["deps"]) for name in deps} == deps
