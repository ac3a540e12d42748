"""What protocol 4's tier verification accepted, and what accepting only narrow intervals would
cost (issue 61: verified tiers that fresh episodes show off their level).

    python benchmarks/verification_budget.py [--fresh [RUN=fresh.json ...]]

Protocol 4 verified a tier whose interval met level ± tolerance at any width; this table over
its records is what decided protocol 5's rule (`oodrl.protocol.tier_search.tier_verified`): a
tier is verified only once its half-width is at most `ci_target` (0.02). On all 21 runs' fresh
checks, none of the 85 tiers verified at ±0.02 fails the goal's test, and 59 of the 387 accepted
wider do (2 of 26 at half-width ≤ 0.025, 3 of 23 at ≤ 0.03, 16 of 79 at ≤ 0.04, 38 of 259
wider), so no wider target is safe; extrapolated to ±0.02, a fault's verification needs 1,300
episodes at the median and 2,510 at the 90th percentile, hence protocol 5's cap of 2,500
(`max_verify_batches` 50 × `verify_batch` 50). On protocol-5 records every verified tier has
met its target: the "not met" column is 0.

Reads the committed impact records of every run (data/impact/*.yaml at the root and in each
pipeline/<run>/): each tier's verification, its episodes, the half-width of its R̃ interval and
whether that reached the search's `ci_target`, and each fault's impact episodes (search and
verification, `tier_search.episodes`). A verification that accepted a tier at a half-width h
from n episodes would need about n (h / w)² episodes for a half-width w (the interval narrows
as 1/√n); the table gives the extra episodes for w = 0.03 (the fresh-data goal's tolerance) and
w = the records' own `ci_target`, against the episodes the impact stages spent. Runs whose
impact records are byte for byte another's (the suite's LunarLander run and the root) count
once in the total.

With --fresh, each RUN's verified tiers are cross-tabulated with the verdict of
`benchmarks/fresh_check.py --json` on fresh episodes (with no RUN=PATH, the checks recorded in
benchmarks/fresh/, RUN.json each; the checks of records since rebuilt are kept in
benchmarks/fresh/protocol-4/), by the protocol version each run was built at and the goal's
test: the level inside the fresh 95% interval or within 0.03 of the fresh estimate; a stepped
tier (its verdict ends in "(step)") passes unless its interval misses its band. Beside the
failures, those expected by chance alone were every tier exactly at its level: the test fails
such a tier with probability P(|Z| > max(1.96, 0.03 / s)) (s the fresh estimate's spread, its
interval's width / 3.92), at most 5% a tier, so a zero is not what a perfect search promises
across a hundred tiers; and those expected were each tier's true R̃ where its verification
measured it (the fresh estimate spread by both intervals): the search aims at the level, so a
search whose intervals are as wide as they should be shows a count between the two. Each
verified tier that fails is then listed with what would have settled it (the goal asks, where
a tier fails, how many episodes the search would need): the verification episodes for its
interval to lie inside level ± tolerance at its estimate, n (h / (tolerance − |R̃ − level|))²,
or none where the estimate itself is off that band (the search must probe another severity).
Reads files only: no simulator runs.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The recorded fresh checks: `fresh_check.py --json` of each run checked, named after it.
FRESH = ROOT / "benchmarks" / "fresh"
#: The fresh-data goal's tolerance (issue 61): a tier passes within 0.03 of the fresh estimate.
GOAL_TOLERANCE = 0.03
#: The standard normal's 97.5% quantile: a 95% interval is the estimate ± Z95 spreads.
Z95 = 1.959964


def runs() -> dict[str, Path]:
    """Run name -> its impact directory: the root's, then every pipeline's."""
    found = {"root": ROOT / "data" / "impact"}
    for directory in sorted((ROOT / "pipeline").glob("*/data/impact")):
        found[directory.parents[1].name] = directory
    return found


def load(path: Path) -> dict:
    from oodrl.io import yamlio  # the project's loader (libyaml where installed)

    return yamlio.load(path.read_text())


def episodes_for(verification: dict, width: float) -> int:
    """Episodes the verification would have needed for a half-width `width`, beyond its own."""
    needed = round(verification["episodes"] * (verification["half_width"] / width) ** 2)
    return max(0, needed - verification["episodes"])


def run_budget(directory: Path) -> dict:
    """One run's verified tiers and what narrower acceptance would add to its impact episodes."""
    counts: Counter = Counter()
    spent = extra_goal = extra_target = 0
    target = None
    for path in sorted(directory.glob("*.yaml")):
        record = load(path)
        target = record["search"]["ci_target"]
        for fault in record["faults"].values():
            spent += fault["tier_search"]["episodes"]["total"]
            for tier in fault["tiers"].values():
                verification = tier.get("verification") or {}
                if not verification.get("verified"):
                    continue
                met = bool(verification["ci_target_met"])
                counts["target met" if met else "target not met"] += 1
                if not met:
                    extra_goal += episodes_for(verification, GOAL_TOLERANCE)
                    extra_target += episodes_for(verification, target)
    return {"counts": counts, "spent": spent, "extra_goal": extra_goal,
            "extra_target": extra_target, "ci_target": target}  # fmt: skip


def digest(directory: Path) -> str:
    hashed = hashlib.sha256()
    for path in sorted(directory.glob("*.yaml")):
        hashed.update(path.name.encode() + b"\0" + path.read_bytes())
    return hashed.hexdigest()


def passes(row: dict) -> bool:
    """The fresh-data goal's test of one tier row of fresh_check.py's JSON."""
    if row["verdict"].endswith("(step)"):
        return not row["verdict"].startswith("misses")
    return row["level_in_ci"] or abs(row["difference"]) <= GOAL_TOLERANCE


def chance_of_failing(row: dict, offset: float = 0.0, half_width: float = 0.0) -> float:
    """The probability that the goal's test fails a tier whose true R̃ lies `offset` from its
    level, from the spread of the fresh estimate (its interval's width as a normal one's),
    widened by a verification interval of `half_width` (the verified estimate as uncertain as
    its interval says: a flat prior's predictive). The test fails when the level is outside the
    fresh interval AND over 0.03 from the estimate: a tier exactly at its level (the defaults)
    fails at most 5% of the time. With the verification's offset and half-width, the tier is
    where verified; the search aims at the level, so a search whose intervals are right shows
    a count between the two. A stepped tier's band is wide: taken as 0."""
    if row["verdict"].endswith("(step)"):
        return 0.0
    low, high = row["ci"]
    fresh = (high - low) / (2 * Z95)
    reach = max(Z95 * fresh, GOAL_TOLERANCE)
    scale = math.sqrt(2) * math.hypot(fresh, half_width / Z95)
    return (math.erfc((reach - offset) / scale) + math.erfc((reach + offset) / scale)) / 2


def episodes_inside_band(verification: dict, level: float, tolerance: float) -> int | None:
    """Verification episodes for the interval to lie inside level ± tolerance (shown to hold)
    at the verified estimate, or None where the estimate itself is off that band (no number of
    episodes at this severity would do: the search must probe another)."""
    room = tolerance - abs(verification["normalised"] - level)
    if room <= 0:
        return None
    return max(
        verification["episodes"],
        round(verification["episodes"] * (verification["half_width"] / room) ** 2),
    )


def failure_lines(failures: list[tuple[str, dict, dict, dict]]) -> list[str]:
    """One row per verified tier failing the goal's test: its verification, the fresh
    estimate, and the episodes that would have shown it to hold (`episodes_inside_band`)."""
    lines = ["", "Verified tiers failing the goal's test:", "",
             "| run | fault | tier | level | verified R̃ ± half-width (episodes) | fresh R̃ [95% CI] "
             "(episodes) | verification episodes to lie inside level ± tolerance |",
             "|---|---|---|---:|---:|---:|---:|"]  # fmt: skip
    for run, row, tier, search in failures:
        verification = tier["verification"]
        needed = episodes_inside_band(verification, tier["level"], search["tolerance"])
        settle = (f"{needed:,}" if needed is not None else
                  f"none: the estimate is off ±{search['tolerance']:g}, the search must probe "
                  "another severity")  # fmt: skip
        low, high = row["ci"]
        lines.append(f"| {run} | {row['fault']} | {row['tier']} | {tier['level']:g} | "
                     f"{verification['normalised']:.3f} ± {verification['half_width']:.3f} "
                     f"({verification['episodes']:,}) | {row['normalised']:.3f} [{low:.3f}, "
                     f"{high:.3f}] ({row['n_episodes']}) | {settle} |")  # fmt: skip
    return lines


def fresh_table(checks: list[tuple[str, Path]], directories: dict[str, Path]) -> list[str]:
    """Verified tiers by whether their verification met its target, and how many of each fail
    the goal's test on fresh episodes (`checks`: run name and fresh_check.py JSON), by the
    protocol version the run was built at, beside how many would fail by chance alone were each
    exactly at its level or where verified (`chance_of_failing`), then the failing ones; a run
    whose records are another's byte for byte counts once. A check of other impact records than
    the committed ones (a tier's severity differs: the run was rebuilt since, e.g. at a new
    protocol version) is left out and named."""
    from oodrl.suite.migration import built_version  # the rule a run's tiers were verified by

    outcome: Counter = Counter()
    chance: Counter = Counter()
    chance_where_verified: Counter = Counter()
    failures = []
    used, other, counted = [], [], set()
    for run, path in checks:
        found = []
        for row in json.loads(path.read_text())["tiers"]["rows"]:
            if row["severity"] == "unreachable":
                continue
            record = load(directories[run] / f"{row['fault']}.yaml")
            tier = record["faults"][row["fault"]]["tiers"][row["tier"]]
            found.append((row, tier, record["search"]))
        if any(tier["severity"] != row["severity"] for row, tier, _ in found):
            other.append(run)
            continue
        used.append(run)
        if (key := digest(directories[run])) in counted:
            continue  # another run's records byte for byte (the root's, the suite's LunarLander)
        counted.add(key)
        version = built_version(directories[run].parents[1])
        for row, tier, search in found:
            verification = tier.get("verification") or {}
            if verification.get("verified"):
                met = f"protocol {version}, target " + ("met" if verification["ci_target_met"]
                                                        else "not met")  # fmt: skip
                outcome[met, passes(row)] += 1
                chance[met] += chance_of_failing(row)
                offset = verification["normalised"] - tier["level"]
                chance_where_verified[met] += chance_of_failing(
                    row, offset, verification["half_width"]
                )
                if not passes(row):
                    failures.append((run, row, tier, search))
    lines = ["", f"Verified tiers on fresh episodes ({len(used)} runs):", "",
             "| verification | tiers | fail the goal's test | expected to fail were each at its "
             "level | were each where verified |", "|---|---:|---:|---:|---:|"]  # fmt: skip
    for met in sorted(chance, reverse=True):  # the newest protocol first
        total = outcome[met, True] + outcome[met, False]
        lines.append(
            f"| {met} | {total} | {outcome[met, False]} | {chance[met]:.1f} | "
            f"{chance_where_verified[met]:.1f} |"
        )
    if failures:
        lines += failure_lines(failures)
    if other:
        lines += ["", f"Left out, checks of other impact records than the committed ones (rebuilt "
                      f"since): {', '.join(other)}."]  # fmt: skip
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fresh", nargs="*", metavar="RUN=PATH")
    args = parser.parse_args()
    directories = runs()
    checks = None
    if args.fresh == []:
        checks = [(path.stem, path) for path in sorted(FRESH.glob("*.json"))]
    elif args.fresh:
        checks = [(run, Path(path)) for run, _, path in (p.partition("=") for p in args.fresh)]
    for run, path in checks or []:
        if run not in directories or not path.is_file():
            parser.error(f"--fresh {run}={path}: RUN must be one of {', '.join(directories)} "
                         "and PATH a fresh_check.py JSON file")  # fmt: skip
    lines = ["| run | verified: target met | not met | impact episodes | +episodes for ±0.03 "
             "| +episodes for the ci_target |", "|---|---:|---:|---:|---:|---:|"]  # fmt: skip
    seen: set[str] = set()
    total = Counter()
    for run, directory in directories.items():
        budget = run_budget(directory)
        counts = budget["counts"]
        lines.append(f"| {run} | {counts['target met']} | {counts['target not met']} | "
                     f"{budget['spent']:,} | {budget['extra_goal']:,} | "
                     f"{budget['extra_target']:,} (±{budget['ci_target']:g}) |")  # fmt: skip
        if (key := digest(directory)) not in seen:
            seen.add(key)
            total.update({**counts, "spent": budget["spent"], "goal": budget["extra_goal"],
                          "target": budget["extra_target"]})  # fmt: skip
    spent = total["spent"]
    lines.append(
        f"| **{len(seen)} distinct** | {total['target met']} | {total['target not met']} | "
        f"{spent:,} | {total['goal']:,} ({(spent + total['goal']) / spent:.2f}×) | "
        f"{total['target']:,} ({(spent + total['target']) / spent:.2f}×) |"
    )
    if checks is not None:
        lines += fresh_table(checks, directories)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
