"""benchmarks/leaderboard_summary.py on a leaderboard built from known results: the top five
in the leaderboard's order, each detector's rank, the audit false-alarm rates over runs, and
where a detector beats another by environment and fault family."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from report.test_leaderboard_report import write_results

from oodrl.io import yamlio
from oodrl.metrics.tier_results import tier_results_text
from oodrl.stages.leaderboard import run_leaderboard

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "leaderboard_summary.py"


def audit(rate_alarmed: int, ci_low: float) -> dict:
    return {"n_alarmed": rate_alarmed, "n_streams": 200, "rate": rate_alarmed / 200,
            "ci": [ci_low, 0.2], "threshold": 1.0}  # fmt: skip


def test_summary_of_a_known_leaderboard(tmp_path: Path):
    """Two environments, five policies each: five cells per (environment, fault family)."""
    strength = {"cusum": 0.5, "kde_density": 0.95, "random_scores": 0.2}
    results = {}
    for seed, (env, policy) in enumerate(
        (env, policy) for env in ("CartPole-v1", "Hopper-v5") for policy in "01234"
    ):
        run = tmp_path / "pipeline" / f"{env}_{policy}" / "reports"
        # q_margin runs on CartPole's runs only (a policy-view detector needs discrete actions)
        # and detects every stream there.
        mine = strength | ({"q_margin": 1.2} if env == "CartPole-v1" else {})
        results[(env, policy)] = write_results(
            run / "results.yaml", seed, mine, tiers=("mild",), detection=True,
            extra={"protocol_version": 3},
        )  # fmt: skip
        tier_results = {"alpha": 0.05, "false_alarm_audit": {
            "cusum": audit(4, 0.01), "kde_density": audit(20, 0.06 if policy == "0" else 0.04),
        }}  # fmt: skip
        # Hopper's runs rebuilt at protocol 5 (JSON), CartPole's still protocol 4's YAML.
        if env == "Hopper-v5":
            (run / "tier_results.json").write_text(tier_results_text(tier_results))
        else:
            (run / "tier_results.yaml").write_text(yamlio.dump(tier_results))
    run_leaderboard(results, tmp_path / "suite", n_boot=200, ci=0.95, seed=0)
    done = subprocess.run(
        [sys.executable, SCRIPT, "--suite", tmp_path / "suite", "--pipelines",
         tmp_path / "pipeline", "--tiers", "mild", "--detectors", "kde_density", "random_scores",
         "q_margin"],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    out = done.stdout
    top = out.split("### Top five at `mild`")[1].split("###")[0]
    assert [line.split(" | ")[1] for line in top.splitlines() if line.startswith("| 1")] == [
        "kde_density"
    ]
    assert "| kde_density | 1/3: " in out and "| random_scores | 3/3: " in out
    # Ranked among the detectors of CartPole's 15 (policy, cell) scores, 3 tasks: marked.
    assert "| q_margin | 1/4: 1.000 [1.000, 1.000] * (3 cells) |" in out
    # 20 of 200 in each run, two of them (policy 0's) above α by their interval.
    assert "| kde_density | 10 | 0.100 | 0.100–0.100 | 0.100 (200/2000) | 2 |" in out
    assert "| cusum | 10 | 0.020 | 0.020–0.020 | 0.020 (40/2000) | 0 |" in out
    beats = out.split("beats `cusum`")[1]
    kde = next(line for line in beats.splitlines() if line.startswith("- **kde_density**"))
    assert "CartPole-v1/observation" in kde and "Hopper-v5/dynamics" in kde
    q_margin = next(line for line in beats.splitlines() if line.startswith("- **q_margin**"))
    assert "CartPole-v1/observation" in q_margin and "Hopper-v5" not in q_margin
    random = next(line for line in beats.splitlines() if line.startswith("- **random_scores**"))
    assert random.endswith("nowhere")
    # Protocol-3 results hold one threshold rule: nothing to compare, said so.
    assert "### What the time-aware rule changes at `mild`: no verified cell holds both" in out
