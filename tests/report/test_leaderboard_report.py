"""The suite's leaderboard report from per-(environment, policy) results files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from oodrl.errors import StoreError
from oodrl.io import yamlio
from oodrl.metrics.tier_results import tier_results_text
from oodrl.report.leaderboard import read_inputs
from oodrl.stages.leaderboard import run_leaderboard

DETECTORS = ("cusum", "kde_density", "pedm")


def write_results(
    path: Path,
    seed: int,
    strength: dict[str, float],
    *,
    tiers: tuple[str | None, ...] = (None,),
    detection: bool = False,
    extra: dict | None = None,
) -> Path:
    """A results file as the metrics stage writes it (a .json path: as the tier_metrics stage
    writes tier results); tier None = a record without a tier."""
    rng = np.random.default_rng(seed)
    records = [
        {"kind": "null", "detector": d, "injector": None, "mode": "posthoc", "metrics": {}}
        for d in strength
    ]
    for tier in tiers:
        for anomaly in ("gaussian_state_noise", "stuck_actuator", "gradual_drift"):
            for d in strength:
                shift = {"mild": -0.2, "moderate": -0.1}.get(tier, 0.0)
                episodes = np.clip(strength[d] + shift + 0.05 * rng.standard_normal(6), 0, 1)
                record = {
                    "kind": "anomaly", "detector": d, "injector": anomaly, "mode": "posthoc",
                    "metrics": {}, "episodes": {"matched_auroc": [float(v) for v in episodes]},
                }  # fmt: skip
                if tier is not None:
                    record["tier"] = tier
                if detection:
                    hits = rng.random(6) < strength[d] + shift
                    record["episodes"]["detection_rate@100"] = [float(h) for h in hits]
                    record["operating_point"] = {"alpha": 0.05, "k": 100}
                records.append(record)
    document = {"records": records} | (extra or {})
    text = tier_results_text(document) if path.suffix == ".json" else yamlio.dump(document)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


@pytest.fixture
def results(tmp_path: Path) -> dict[str, Path]:
    return {
        "CartPole-v1": write_results(
            tmp_path / "a" / "results.yaml", 0, {"cusum": 0.9, "kde_density": 0.6, "pedm": 0.7}
        ),
        "Pendulum-v1": write_results(
            tmp_path / "b" / "results.yaml", 1, {"cusum": 0.8, "kde_density": 0.55, "pedm": 0.9}
        ),
    }


def table_rows(markdown: str, heading: str) -> list[str]:
    """The first column of the first table after the line starting with `heading`."""
    lines = markdown.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(heading))
    rows = []
    for line in lines[start + 4 :]:
        if not line.startswith("|"):
            break
        rows.append(line.split(" | ")[0].lstrip("| "))
    return rows


def test_todays_results_build_the_headline_table_and_reproduce(results, tmp_path: Path):
    board = run_leaderboard(results, tmp_path / "out", n_boot=200, ci=0.95, seed=0)
    lead = board.overall[board.lead]
    assert board.lead == ("matched_auroc", "headline")
    assert lead.n_cells == 6 and lead.environments == ("CartPole-v1", "Pendulum-v1")
    assert lead.bootstrap == "episodes"
    table = (tmp_path / "out" / "leaderboard.md").read_text()
    heading = "## Tier `headline`: mean matched AUROC per detector and environment (6 cells)"
    assert table_rows(table, heading) == ["cusum", "pedm", "kde_density"]  # by IQM
    assert "| detector | CartPole-v1 | Pendulum-v1 | IQM [95% CI] | mean [95% CI] |" in table
    assert "episodes resampled within each cell (one run per cell)" in table
    assert "One policy (policy 0): nothing to compare." in table
    assert "Protocol version 1 (unstamped results)" in table
    assert "None of them is in the results: no cell is flagged." in table
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    lead = "matched_auroc.headline.iqm."  # every key names its metric, tier and aggregate
    assert metrics[f"{lead}cusum"] > metrics[f"{lead}pedm"] > metrics[f"{lead}kde_density"]
    assert (tmp_path / "out" / "leaderboard.png").read_bytes()[:4] == b"\x89PNG"
    first = {p.name: p.read_bytes() for p in (tmp_path / "out").iterdir()}
    run_leaderboard(results, tmp_path / "again", n_boot=200, ci=0.95, seed=0)
    assert first == {p.name: p.read_bytes() for p in (tmp_path / "again").iterdir()}


def test_tiers_policies_operating_points_flags_and_mdi(tmp_path: Path):
    strength = {"cusum": 0.9, "kde_density": 0.6, "pedm": 0.7, "time_index": 0.97}
    mdi = {"minimum_detectable_impact": {
        "cusum": {"gradual_drift": {"matched_auroc": 0.031, "detection_rate@100": "beyond range"}},
        "pedm": {"gradual_drift": {"matched_auroc": 0.12}},
        # Reached already at the first measured tier: a bound (SPEC §19).
        "kde_density": {"gradual_drift": {"matched_auroc": {"at_most": 0.05}}},
    }}  # fmt: skip
    results = {
        (env, policy): write_results(
            tmp_path / env / policy / "results.yaml",
            seed,
            strength,
            tiers=("severe", "mild"),
            detection=True,
            extra=mdi | {"protocol_version": 2},
        )  # fmt: skip
        for seed, (env, policy) in enumerate(
            [("CartPole-v1", "0"), ("CartPole-v1", "1"), ("Hopper-v5", "0"), ("Hopper-v5", "1")]
        )
    }
    board = run_leaderboard(results, tmp_path / "out", n_boot=100, ci=0.95, seed=0)
    assert board.lead == ("detection_rate@100", "mild")
    assert board.overall[board.lead].bootstrap == "runs"
    assert board.overall[board.lead].runs == (2,) * 6
    text = (tmp_path / "out" / "leaderboard.md").read_text()
    headings = [line for line in text.splitlines() if line.startswith("## ")]
    assert headings[0].startswith(
        "## Tier `mild`: mean detection_rate@100 at α = 0.05 per detector and environment"
    )
    assert headings[1].startswith("## Tier `mild`: mean matched AUROC")
    assert headings[2].startswith("## Tier `severe`")
    assert "Protocol version 2;" in text and "2 policies (0, 1)" in text
    assert "policies (runs) resampled within each cell" in text
    assert "### By fault family" in text and "observation (2 cells)" in text
    assert "Kendall τ between per-policy rankings (by IQM): 0–1:" in text
    # time_index (0.97, −0.2 at mild) detects every cell at severe: all flagged there.
    assert "CartPole-v1 / gradual_drift / severe | time_index" in text
    assert "| time_index (trivial signal) |" in text
    assert (
        "## Minimum detectable impact: the smallest return loss 1 − R̃ at which matched AUROC "
        "reaches 0.9" in text
    )
    assert "| CartPole-v1 / policy 0 / gradual_drift | 3.1% | ≤ 5.0% | 12.0% |" in text
    assert "| beyond range |" in text
    document = yamlio.load((tmp_path / "out" / "leaderboard.yaml").read_text())
    assert document["protocol_version"] == 2 and document["alpha"] == 0.05
    mild = document["boards"]["detection_rate@100"]["mild"]
    assert len(mild["performance_profile"]["taus"]) == 51
    assert mild["stability"]["policies"] == ["0", "1"]
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert {"detection_rate@100.mild.iqm.cusum", "matched_auroc.severe.iqm.cusum"} <= set(metrics)
    assert all(len(key.split(".")) >= 4 for key in metrics)  # metric, tier, aggregate, detector


def test_mixed_protocol_versions_are_refused_before_anything_is_written(results, tmp_path: Path):
    newer = write_results(
        tmp_path / "c" / "results.yaml", 2, {d: 0.7 for d in DETECTORS},
        extra={"protocol_version": 2, "params_hash": "sha256:0"},
    )  # fmt: skip
    with pytest.raises(StoreError) as error:
        run_leaderboard(results | {"Hopper-v5": newer}, tmp_path / "out", 50, 0.95, 0)
    message = str(error.value)
    assert "\n" not in message and "cannot be ranked together" in message
    assert f"version 1: {results['CartPole-v1']}, {results['Pendulum-v1']}" in message
    assert f"version 2: {newer}" in message
    assert not (tmp_path / "out").exists()


def test_missing_old_or_partial_results_are_one_line_errors(results, tmp_path: Path):
    with pytest.raises(StoreError, match="results of Hopper-v5 are missing"):
        read_inputs({**results, "Hopper-v5": tmp_path / "nowhere.yaml"})
    old = tmp_path / "old.yaml"
    old.write_text(yamlio.dump({"records": [{"kind": "anomaly", "detector": "x", "anomaly": "y"}]}))
    with pytest.raises(StoreError, match="re-run Acrobot-v1's metrics stage"):
        read_inputs({"Acrobot-v1": old})
    partial = write_results(
        tmp_path / "d" / "results.yaml", 3, {d: 0.7 for d in DETECTORS}, detection=True
    )
    with pytest.raises(StoreError, match="lacks per-episode detection_rate@100"):
        read_inputs(results | {"Hopper-v5": partial})
    # A run may run fewer detectors than another (its params'), never fewer in one of its cells.
    gap = write_results(tmp_path / "e" / "results.yaml", 4, {d: 0.7 for d in DETECTORS})
    document = yamlio.load(gap.read_text())
    document["records"] = [
        r for r in document["records"]
        if (r["detector"], r.get("injector")) != ("kde_density", "gradual_drift")
    ]  # fmt: skip
    gap.write_text(yamlio.dump(document))
    with pytest.raises(StoreError, match="no records of kde_density on .*'gradual_drift'"):
        read_inputs(results | {"Hopper-v5": gap})


def test_a_detector_that_runs_on_some_runs_is_ranked_where_it_runs(results, tmp_path: Path):
    """Hopper's run has no kde_density (as a continuous-action run has no policy-view detector):
    the lead board ranks the detectors every cell has; kde_density is ranked beside them over the
    cells of the runs that have it, in the tables, metrics.json and the page's data."""
    fewer = write_results(tmp_path / "c" / "results.yaml", 2, {"cusum": 0.9, "pedm": 0.7})
    board = run_leaderboard(
        results | {"Hopper-v5": fewer}, tmp_path / "out", n_boot=200, ci=0.95, seed=0
    )
    key = ("matched_auroc", "headline")
    assert board.overall[key].detectors == ("cusum", "pedm") and board.overall[key].n_cells == 9
    (scope,) = board.scoped[key]
    assert scope.detectors == DETECTORS and scope.environments == ("CartPole-v1", "Pendulum-v1")
    assert scope.n_cells == 6
    text = (tmp_path / "out" / "leaderboard.md").read_text()
    assert "### Where more detectors run: CartPole-v1, Pendulum-v1 (6 cells)\n" in text
    assert table_rows(text, "kde_density run only on these cells") == [
        "cusum", "pedm", "kde_density"
    ]  # fmt: skip
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert "matched_auroc.headline.iqm.kde_density" not in metrics
    scoped = "matched_auroc.headline.CartPole-v1+Pendulum-v1.iqm.kde_density"
    assert metrics[scoped] == round(scope.iqm["kde_density"].value, 6)
    page = json.loads((tmp_path / "out" / "leaderboard.json").read_text())
    (entry,) = page["iqm_where_more_detectors_run"]["matched_auroc"]["headline"]
    assert entry["n_cells"] == 6 and set(entry["iqm"]) == set(DETECTORS)


def test_the_stage_reads_headline_and_tier_results_of_every_environment(tmp_path: Path):
    from oodrl.config import parse_params
    from oodrl.metrics.tier_results import PROTOCOL_4_TIER_RESULTS, TIER_RESULTS
    from oodrl.stages.leaderboard import HEADLINE_RESULTS, results_files, run
    from oodrl.suite.environments import PIPELINE_DIRS, suite_runs

    strength = {"cusum": 0.9, "kde_density": 0.6, "pedm": 0.7}
    stamp = {"protocol_version": 2, "params_hash": "sha256:0"}
    for seed, directory in enumerate(suite_runs().values()):  # every run: a missing one fails
        write_results(tmp_path / directory / HEADLINE_RESULTS, seed, strength, extra=stamp)
        if seed < 3:  # the impact tiers scored in three environments, one rebuilt (JSON)
            tiers = TIER_RESULTS if seed == 0 else PROTOCOL_4_TIER_RESULTS
            write_results(
                tmp_path / directory / tiers, 100 + seed, strength,
                tiers=("mild", "moderate"), detection=True, extra=stamp,
            )  # fmt: skip
    files = results_files(tmp_path)
    assert set(files) == set(suite_runs())
    assert sum(len(paths) for paths in files.values()) == len(suite_runs()) + 3
    params = parse_params(
        {"benchmark": {"detectors": ["cusum"], "injectors": ["gradual_drift"]},
         "detectors": {"cusum": {}}, "anomaly": {"injectors": {"gradual_drift": {}}},
         "metrics": {"n_boot": 50}},
        "params", components=False,
    )  # fmt: skip
    run(params, tmp_path, tmp_path / "out")
    text = (tmp_path / "out" / "leaderboard.md").read_text()
    headings = [
        line.split(" per detector")[0] for line in text.splitlines() if line.startswith("## Tier")
    ]
    assert headings == [
        "## Tier `mild`: mean detection_rate@100 at α = 0.05",
        "## Tier `mild`: mean matched AUROC",
        "## Tier `moderate`: mean detection_rate@100 at α = 0.05",
        "## Tier `moderate`: mean matched AUROC",
        "## Tier `headline`: mean matched AUROC",
    ]
    assert f"({len(PIPELINE_DIRS) * 3} cells)" in text  # the headline tier: every environment


def test_one_cell_one_record(results, tmp_path: Path):
    again = {"CartPole-v1": [results["CartPole-v1"], results["CartPole-v1"]]}
    with pytest.raises(StoreError, match="a second record of cusum on"):
        read_inputs(again)


def test_benign_cells_rank_the_quietest_first_and_unverified_cells_are_left_out(tmp_path: Path):
    """SPEC §19: a detection at `benign` is a false alarm (lower is better); the harm view sets
    it beside `mild`; a cell whose tier verification missed is in no aggregate, and listed."""
    strength = {"cusum": 0.9, "kde_density": 0.3, "pedm": 0.6}
    results = {}
    for seed, env in enumerate(("CartPole-v1", "Hopper-v5")):
        path = write_results(
            tmp_path / env / "results.yaml", seed, strength, tiers=("mild", "benign"),
            detection=True, extra={"protocol_version": 3},
        )  # fmt: skip
        document = yamlio.load(path.read_text())
        for record in document["records"]:
            if record.get("tier") is not None:
                # Hopper's benign gradual_drift tier missed its verification.
                missed = (env, record["tier"], record["injector"]) == (
                    "Hopper-v5", "benign", "gradual_drift"
                )  # fmt: skip
                record["verified"] = not missed
        path.write_text(yamlio.dump(document))
        results[env] = path
    inputs = read_inputs(results)
    assert inputs.unverified == (("Hopper-v5", "0", "gradual_drift", "benign"),)
    board = run_leaderboard(results, tmp_path / "out", n_boot=100, ci=0.95, seed=0)
    assert board.overall[("detection_rate@100", "benign")].n_cells == 5  # 6 less the missed one
    assert board.overall[("detection_rate@100", "mild")].n_cells == 6
    table = (tmp_path / "out" / "leaderboard.md").read_text()
    heading = "## Tier `benign`: mean detection_rate@100"
    benign = board.overall[("detection_rate@100", "benign")]
    quietest_first = sorted(strength, key=lambda d: (benign.iqm[d].value, d))
    assert table_rows(table, heading)[2:] == quietest_first  # after the note and the rule
    assert "an alarm here is a cost, so lower is better" in table
    assert "## Detects what hurts, stays quiet on what does not" in table
    assert "1 cell whose tier's verification missed its level" in table
    assert "Hopper-v5/0/gradual_drift/benign" in table


def test_the_floor_is_marked_and_detectors_not_above_it_are_named(tmp_path: Path):
    """SPEC §20: `random_scores` is the floor; a detector whose P(beats the floor) has its CI
    above ½ is above it, one that scores like the floor is named as not above it."""
    strength = {"cusum": 0.9, "kde_density": 0.5, "random_scores": 0.5}
    results = {
        env: write_results(
            tmp_path / env / "results.yaml",
            seed,
            strength,
            tiers=("mild",),
            detection=True,
            extra={"protocol_version": 3},
        )  # fmt: skip
        for seed, env in enumerate(("CartPole-v1", "Hopper-v5", "Pendulum-v1"))
    }
    board = run_leaderboard(results, tmp_path / "out", n_boot=200, ci=0.95, seed=0)
    table = (tmp_path / "out" / "leaderboard.md").read_text()
    rows = table_rows(table, "## Tier `mild`: mean detection_rate@100")
    assert "random_scores (floor)" in rows
    mild = board.overall[("detection_rate@100", "mild")]
    assert mild.improvement[("cusum", "random_scores")].ci_low > 0.5
    assert "1 of 2 do. Not above the floor: kde_density." in table
    page = json.loads((tmp_path / "out" / "leaderboard.json").read_text())
    assert page["floor_detector"] == "random_scores"


def _rule_results(
    path: Path, gains: dict[str, float] | None, more: dict[str, float] | None = None,
    streams: int = 40,
) -> Path:  # fmt: skip
    """Tier results whose records hold both rules' detections per stream (`gains`: the
    detectors' time-aware rate minus their constant rate), or the constant rule's only (None:
    results of protocol 3); `more`: detectors of this run only, with their constant rate."""
    strength = {"cusum": 0.8, "kde_density": 0.3, "pedm": 0.5, **(more or {})}
    records = []
    for tier in ("mild", "moderate"):
        for fault in ("gaussian_state_noise", "stuck_actuator", "gradual_drift"):
            for d, rate in strength.items():
                hits = (np.arange(streams) < rate * streams).astype(float)
                episodes = {"matched_auroc": [0.7] * streams, "detection_rate@100": hits.tolist()}
                if gains is not None:
                    gained = np.arange(streams) < (rate + gains.get(d, 0.0)) * streams
                    episodes["time_aware_detection_rate@100"] = gained.astype(float).tolist()
                records.append({
                    "kind": "anomaly", "detector": d, "injector": fault, "mode": "online",
                    "tier": tier, "verified": True, "metrics": {}, "episodes": episodes,
                    "operating_point": {"alpha": 0.05, "k": 100},
                })  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yamlio.dump({"protocol_version": 4, "records": records}))
    return path


def test_what_the_time_aware_rule_changes_pairs_the_rules_where_results_hold_both(tmp_path):
    """SPEC §24: per detector, time-aware minus constant over the cells whose records hold both
    rules (a run of protocol 3 holds one: not in it), with its paired bootstrap CI and Kendall
    τ; in leaderboard.md, .yaml and .json, never ranked as a metric of its own."""
    results = {
        # q_margin runs on CartPole only (as the policy view on a discrete-action run).
        "CartPole-v1": _rule_results(
            tmp_path / "a.yaml", {"kde_density": 0.5, "q_margin": 0.1}, {"q_margin": 0.2}
        ),
        "Hopper-v5": _rule_results(tmp_path / "b.yaml", {"kde_density": 0.5}),
        "Pendulum-v1": _rule_results(tmp_path / "c.yaml", None),
    }
    board = run_leaderboard(results, tmp_path / "out", n_boot=200, ci=0.95, seed=0)
    assert board.metrics == ("detection_rate@100", "matched_auroc")  # not ranked itself
    change = board.rule_change[("detection_rate@100", "mild")]
    assert (change.n_cells, change.n_tier_cells) == (6, 9)
    assert change.detectors == ["cusum", "kde_density", "pedm", "q_margin"]
    environments, common = change.scopes[0]
    assert environments == ("CartPole-v1", "Hopper-v5")
    kde, cusum = common.differences["kde_density"], common.differences["cusum"]
    assert kde.mean == pytest.approx(0.5) and kde.excludes_zero and kde.n_cells == 6
    assert (cusum.mean, cusum.ci_low, cusum.ci_high) == (0.0, 0.0, 0.0)
    assert not cusum.excludes_zero
    # Only kde_density moves (0.3 -> 0.8), past pedm and level with cusum: τ below 1.
    assert common.kendall_tau < 1
    scope, q_margin = change.of("q_margin")
    assert scope == ("CartPole-v1",) and q_margin.differences["q_margin"].n_cells == 3

    text = (tmp_path / "out" / "leaderboard.md").read_text()
    heading = "## What the time-aware rule changes: detection_rate@100 at α = 0.05"
    assert text.count(heading) == 1
    section = text[text.index(heading) :]
    assert "| detector | mild: time-aware − constant [95% CI] | moderate: time-aware" in section
    # The lead board's order (the constant rule's), then a detector it does not rank.
    assert table_rows(section, heading)[2:6] == ["cusum", "pedm", "kde_density", "q_margin"]
    assert "| kde_density | +0.500 [" in section and "] * |" in section
    assert "| cusum | +0.000 [+0.000, +0.000] |" in section
    assert "| cells with both rules | 6 of 9 | 6 of 9 |" in section
    assert "† over the cells where the detector runs" in section
    assert "time_aware_detection_rate" not in text
    document = yamlio.load((tmp_path / "out" / "leaderboard.yaml").read_text())
    assert set(document["boards"]) == {"detection_rate@100", "matched_auroc"}
    mild = document["rule_change"]["detection_rate@100"]["mild"]
    assert mild["n_cells"] == 6 and mild["detectors"]["kde_density"]["changed"] is True
    assert mild["detectors"]["kde_density"]["difference"]["value"] == 0.5
    assert mild["detectors"]["q_margin"]["environments"] == ["CartPole-v1"]
    assert mild["kendall_tau"][0]["tau"] == round(common.kendall_tau, 6)
    page = json.loads((tmp_path / "out" / "leaderboard.json").read_text())
    assert page["rule_change"] == document["rule_change"]
    assert all(set(c["scores"]) <= set(page["metrics"]) for c in page["cells"])
    assert 'id="rule-change-section"' in (tmp_path / "out" / "leaderboard.html").read_text()

    # Results of protocol 3 alone: nothing to compare, no key, no section.
    run_leaderboard({"Pendulum-v1": results["Pendulum-v1"]}, tmp_path / "old", 50, 0.95, 0)
    assert "rule_change" not in yamlio.load((tmp_path / "old" / "leaderboard.yaml").read_text())
    assert "rule_change" not in json.loads((tmp_path / "old" / "leaderboard.json").read_text())
    assert "time-aware" not in (tmp_path / "old" / "leaderboard.md").read_text()
