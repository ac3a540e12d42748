"""benchmarks/verification_budget.py: the episodes a narrower verification would need, the
goal's test of a fresh tier row, and its table over the committed impact records."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest
from benchmark_scripts import BENCHMARKS, load_benchmark

from oodrl.suite.migration import built_version

SCRIPT = BENCHMARKS / "verification_budget.py"


@pytest.fixture(scope="module")
def budget():
    return load_benchmark("verification_budget")


def test_a_half_width_halved_takes_four_times_the_episodes(budget):
    assert budget.episodes_for({"episodes": 50, "half_width": 0.06}, 0.03) == 150
    assert budget.episodes_for({"episodes": 100, "half_width": 0.02}, 0.03) == 0


@pytest.mark.parametrize(
    ("verdict", "level_in_ci", "difference", "passes"),
    [
        ("undecided at 150 episodes", False, -0.031, False),
        ("undecided at 150 episodes", False, 0.029, True),
        ("undecided at 150 episodes", True, -0.05, True),
        ("undecided at 150 episodes (step)", False, -0.14, True),  # its band, not its level
        ("misses by -0.200 (step)", False, -0.2, False),
    ],
)
def test_the_goals_test_of_a_fresh_row(budget, verdict, level_in_ci, difference, passes):
    row = {"verdict": verdict, "level_in_ci": level_in_ci, "difference": difference}
    assert budget.passes(row) is passes


def _with_root_check(rows: list[dict], tmp_path) -> str:
    """The script's output with `rows` as the root's fresh check (fresh_check.py's JSON)."""
    fresh = tmp_path / "fresh.json"
    fresh.write_text(json.dumps({"tiers": {"rows": rows}}))
    return subprocess.run(
        [sys.executable, str(SCRIPT), "--fresh", f"root={fresh}"],
        capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip


def test_the_table_has_a_row_per_run_and_counts_shared_records_once(budget, tmp_path):
    runs = budget.runs()
    # One fresh row per verified tier of the root's first fault: each passes.
    fault_path = sorted(runs["root"].glob("*.yaml"))[0]
    fault = fault_path.stem
    tiers = budget.load(fault_path)["faults"][fault]["tiers"]
    verified = [
        name for name, tier in tiers.items() if (tier.get("verification") or {}).get("verified")
    ]
    rows = [
        {"fault": fault, "tier": name, "severity": tiers[name]["severity"],
         "ci": [tiers[name]["level"] - 0.01, tiers[name]["level"] + 0.01],
         "verdict": "within 0.02", "level_in_ci": True, "difference": 0.0}
        for name in verified
    ]  # fmt: skip
    out = _with_root_check(rows, tmp_path)
    table = [line for line in out.splitlines() if line.startswith("| ")]
    assert [line.split(" | ")[0][2:] for line in table[1 : len(runs) + 1]] == list(runs)
    # Runs whose records are another's byte for byte count once (during a change of protocol
    # the root and the suite's LunarLander run may differ, so the total is computed, not assumed).
    first = {}
    for directory in runs.values():
        first.setdefault(budget.digest(directory), directory)
    spent = sum(budget.run_budget(directory)["spent"] for directory in first.values())
    total = next(line for line in table if line.startswith("| **")).split(" | ")
    assert total[0] == f"| **{len(first)} distinct**" and total[3] == f"{spent:,}"
    met = sum(tiers[n]["verification"]["ci_target_met"] for n in verified)
    version = built_version(runs["root"].parents[1])
    # Intervals of ±0.01 around the level: no chance of failing the test (0.03 is ~6 spreads).
    expected = [
        f"| protocol {version}, target {label} | {n} | 0 | 0.0 |"
        for label, n in (("met", met), ("not met", len(verified) - met))
        if n  # a verification kind no tier had gets no row
    ]
    assert [line for line in table if line.startswith("| protocol")] == expected


def test_without_paths_it_reads_the_recorded_checks():
    recorded = sorted(BENCHMARKS.glob("fresh/*.json"))
    out = subprocess.run(
        [sys.executable, str(SCRIPT), "--fresh"], capture_output=True, text=True, check=True
    ).stdout
    used = int(re.search(r"Verified tiers on fresh episodes \((\d+) runs\):", out)[1])
    left = re.search(r"\(rebuilt since\): (.*)\.$", out, re.MULTILINE)
    assert recorded and used + (len(left[1].split(", ")) if left else 0) == len(recorded)


def test_a_check_of_other_records_is_left_out_and_named(tmp_path):
    """A fresh check made before its run was rebuilt (another severity) is not cross-tabulated
    with the new records."""
    fault = sorted(load_benchmark("verification_budget").runs()["root"].glob("*.yaml"))[0].stem
    rows = [{"fault": fault, "tier": "severe", "severity": 12.5, "verdict": "within 0.02",
             "level_in_ci": True, "difference": 0.0}]  # fmt: skip
    out = _with_root_check(rows, tmp_path)
    assert "Verified tiers on fresh episodes (0 runs):" in out
    assert out.rstrip().endswith("(rebuilt since): root.")


def test_the_chance_that_the_test_fails_a_tier_exactly_at_its_level(budget):
    wide = {"verdict": "undecided at 150 episodes", "ci": [0.9108, 0.9892]}  # spread 0.02
    # 0.03 is 1.5 spreads, inside the interval: the interval decides, 5%.
    assert budget.chance_of_failing(wide) == pytest.approx(0.05, abs=1e-6)
    narrow = {"verdict": "within 0.02", "ci": [0.94, 0.96]}  # 0.03 is about 5.9 spreads
    assert budget.chance_of_failing(narrow) < 1e-8
    assert budget.chance_of_failing({**wide, "verdict": "undecided at 150 episodes (step)"}) == 0


def test_the_chance_that_the_test_fails_a_tier_where_it_was_verified(budget):
    row = {"verdict": "undecided at 150 episodes", "ci": [0.9108, 0.9892]}  # spread 0.02
    # The verification's own interval widens the fresh estimate's spread: more failures.
    assert budget.chance_of_failing(row, 0.0, 0.02) > budget.chance_of_failing(row)
    # At the band's edge (0.015 off; the interval decides, at ±0.039) about one in nine fails,
    # either side; far off, nearly every one.
    edge = budget.chance_of_failing(row, 0.015)
    assert 0.1 < edge < 0.13 and budget.chance_of_failing(row, -0.015) == pytest.approx(edge)
    for offset in (-0.1, 0.1):
        assert budget.chance_of_failing(row, offset, 0.01) > 0.99
    stepped = {**row, "verdict": "within 0.02 (step)"}
    assert budget.chance_of_failing(stepped, 0.1, 0.02) == 0


def test_the_episodes_that_would_show_a_tier_inside_its_band(budget):
    verification = {"episodes": 100, "half_width": 0.02, "normalised": 0.94}
    # 0.01 of room on either side of the estimate: the half-width halved, four times the episodes.
    assert budget.episodes_inside_band(verification, 0.95, 0.02) == 400
    # An interval already inside the band needs no more than it had.
    assert budget.episodes_inside_band(verification, 0.94, 0.03) == 100
    # An estimate off the band is not settled by episodes at this severity.
    assert budget.episodes_inside_band(verification, 0.97, 0.02) is None


def test_a_verified_tier_failing_on_fresh_episodes_is_listed(budget, tmp_path):
    fault, name, tier, record = next(
        (path.stem, name, tier, record)
        for path in sorted(budget.runs()["root"].glob("*.yaml"))
        for record in [budget.load(path)]
        for name, tier in record["faults"][path.stem]["tiers"].items()
        if (tier.get("verification") or {}).get("verified")
    )  # fmt: skip
    row = {"fault": fault, "tier": name, "severity": tier["severity"], "n_episodes": 150,
           "normalised": tier["level"] - 0.05, "ci": [tier["level"] - 0.08, tier["level"] - 0.04],
           "verdict": "misses by -0.050", "level_in_ci": False, "difference": -0.05}  # fmt: skip
    out = _with_root_check([row], tmp_path)
    assert re.search(
        r"^\| protocol \d, target (not )?met \| 1 \| 1 \| \d\.\d \| \d\.\d \|$", out, re.M
    )
    listed = out.splitlines()[-1].split(" | ")
    assert listed[:4] == ["| root", fault, name, f"{tier['level']:g}"]
    needed = budget.episodes_inside_band(tier["verification"], tier["level"],
                                         record["search"]["tolerance"])  # fmt: skip
    assert listed[-1].startswith(f"{needed:,} |" if needed is not None else "none: ")


def test_an_unknown_run_is_a_usage_error():
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--fresh", "nowhere=missing.json"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert done.returncode == 2
    assert (
        done.stderr.strip()
        .splitlines()[-1]
        .startswith(
            "verification_budget.py: error: --fresh nowhere=missing.json: RUN must be one of root"
        )
    )
