"""Keep the generated tables of README.md and the docs equal to what the pipelines generated.

A generated block sits between a start marker and `<!-- headline:end -->`; `oodrl readme-table
SOURCE --readme FILE` rewrites it from SOURCE, and the tests check every committed block is
current. There are two kinds, told apart by the source:

- `<!-- headline:start leaderboard -->`: the suite's leaderboard headline, rendered from
  `pipeline/suite/reports/leaderboard.json` (README.md's first screen): the lead tier's top
  detectors by IQM with 95% CIs, beside their matched AUROC, their alarm rate on harmless
  (`benign`) shifts and, where the results hold both threshold rules (protocol 4), what the
  time-aware rule changes of the lead metric (SPEC §24).
- `<!-- headline:start -->`: a pipeline's per-detector table, `reports/headline.md`, copied as
  the render stage wrote it (docs/getting-started.md, "Reading the results").
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from oodrl.errors import StoreError

START, END = "<!-- headline:start -->", "<!-- headline:end -->"
LEADERBOARD_START = "<!-- headline:start leaderboard -->"
#: The suite's leaderboard, from the repository root; README.md's headline is rendered from it.
LEADERBOARD = Path("pipeline/suite/reports/leaderboard.json")
#: Detectors in README.md's headline table (the rest are on the leaderboard page).
TOP = 5
#: The harmless-shift control the headline sets beside the lead tier (SPEC §19).
HARMLESS_TIER = "benign"
#: The threshold-free metric the headline sets beside the lead metric.
THRESHOLD_FREE = "matched_auroc"


def _interval(entry: dict[str, float]) -> str:
    return f"{entry['value']:.3f} [{entry['ci_low']:.3f}, {entry['ci_high']:.3f}]"


def _signed_interval(entry: dict[str, float]) -> str:
    return f"{entry['value']:+.3f} [{entry['ci_low']:+.3f}, {entry['ci_high']:+.3f}]"


def _name(board: dict[str, Any], detector: str) -> str:
    name = f"`{detector}`"
    if detector in board.get("uncertified_detectors", []):
        name += " †"
    return name


def leaderboard_headline(board: dict[str, Any], top: int = TOP) -> str:
    """The lead tier's top `top` detectors by IQM of the lead metric, with 95% CIs, as Markdown.

    `board` is the suite's leaderboard.json. Each row also gives the detector's IQM of matched
    AUROC at the lead tier and its alarm rate on the harmless tier (lower is better there); the
    caption says what the numbers are over and where the floor detector lands.
    """
    lead = board["lead"]
    metric, tier = lead["metric"], lead["tier"]
    scores = board["iqm"][metric][tier]
    # The leaderboard's own order breaks ties; a detector of the main table is in `scores`.
    order = {name: rank for rank, name in enumerate(board["detectors"])}
    ranked = sorted(scores, key=lambda d: (-scores[d]["value"], order.get(d, len(order))))
    floor, trivial = board.get("floor_detector"), set(board.get("trivial_detectors", []))
    shown = [d for d in ranked if d != floor and d not in trivial][:top]
    auroc = board["iqm"].get(THRESHOLD_FREE, {}).get(tier, {})
    harmless = board["iqm"][metric].get(HARMLESS_TIER, {})
    # Absent before protocol 4, whose results hold one threshold rule.
    rule_change = board.get("rule_change", {}).get(metric, {}).get(tier)
    alpha = board["alpha"]
    header = [
        "rank",
        "detector",
        f"{tier}: detected within {metric.split('@')[-1]} steps at α = {alpha:g}",
        f"{tier}: matched AUROC",
        f"{HARMLESS_TIER}: alarm rate (lower is better)",
    ]
    if rule_change:
        header.append(f"{tier}, detected: time-aware rule − constant")
    lines = [
        "| " + " | ".join(header) + " |",
        "|" + "|".join(["---:", "---"] + ["---:"] * (len(header) - 2)) + "|",
    ]
    for detector in shown:
        cells = [
            str(ranked.index(detector) + 1),
            _name(board, detector),
            f"**{_interval(scores[detector])}**",
            _interval(auroc[detector]) if detector in auroc else "—",
            _interval(harmless[detector]) if detector in harmless else "—",
        ]
        if rule_change:
            change = rule_change["detectors"].get(detector)
            cells.append(
                _signed_interval(change["difference"]) + (" *" if change["changed"] else "")
                if change
                else "—"
            )
        lines.append("| " + " | ".join(cells) + " |")
    mild = [c for c in board["cells"] if c["tier"] == tier]
    n_cells = len({(c["environment"], c["fault"]) for c in mild})
    caption = (
        f"IQM over the {len(mild)} (policy, cell) scores of the {n_cells} `{tier}` "
        f"(environment, fault) cells of {len(board['runs'])} runs "
        f"({len(board['environments'])} environments × {len(board['policies'])} policies), "
        f"stratified-bootstrap 95% CIs; protocol version {board['protocol_version']}; "
        f"top {len(shown)} of {len(scores)} detectors"
    )
    if floor in scores:
        caption += f"; the floor, `{floor}`: {_interval(scores[floor])}"
    caption += "."
    if rule_change:
        caption += " " + _rule_change_caption(rule_change, tier)
    if board.get("pending"):  # a change of protocol under way (SPEC §26): say what is left out
        runs = ", ".join(
            f"{r['environment']}/{r['policy']} (protocol {r['protocol_version']})"
            for r in board["pending"]
        )
        caption += f" Pending, ranked by none of these numbers: {runs}."
    if any(d in board.get("uncertified_detectors", []) for d in shown):
        caption += " † runs a library's own kernels (not certified machine-independent)."
    return "\n".join([*lines, "", caption])


def _rule_change_caption(rule_change: dict[str, Any], tier: str) -> str:
    """What the last column is over (`rule_change_mapping`'s record of the lead tier)."""
    everywhere = rule_change["kendall_tau"][0]  # the detectors that run on every environment
    return (
        "Last column: the detection rate under the time-aware per-stream threshold rule minus "
        "under the constant one, on the same streams (mean over the "
        f"{rule_change['n_cells']} of {rule_change['n_tier_cells']} `{tier}` cells whose results "
        "hold both; paired-bootstrap 95% CI, * where it excludes 0); Kendall τ of the two rules' "
        f"IQM rankings {everywhere['tau']:.2f} over the {len(everywhere['detectors'])} detectors "
        f"run on all {len(everywhere['environments'])} environments."
    )


def _source_block(headline: Path) -> tuple[str, str]:
    """The start marker a source fills and the block's text."""
    if not headline.is_file():
        hint = (
            "run `dvc repro` in pipeline/suite first."
            if headline.suffix == ".json"
            else "run `dvc repro render` first."
        )
        raise StoreError(f"{headline}: missing; {hint}")
    if headline.suffix == ".json":
        try:
            board = json.loads(headline.read_text())
            return LEADERBOARD_START, leaderboard_headline(board)
        except (ValueError, KeyError, TypeError) as error:
            raise StoreError(f"{headline}: not a suite leaderboard ({error!r}).") from None
    return START, headline.read_text().strip()


def generated_block(text: str, start: str) -> str | None:
    """The text between `start` and the next END marker, stripped; None without the markers."""
    if start not in text:
        return None
    rest = text.split(start, 1)[1]
    if END not in rest:
        return None
    return rest.split(END, 1)[0].strip()


def insert_headline(readme: Path, headline: Path) -> None:
    """Rewrite `readme`'s generated block of `headline`'s kind from `headline`."""
    from oodrl.io.fileio import atomic_write_text

    start, block = _source_block(headline)
    text = readme.read_text()
    if generated_block(text, start) is None:
        other = (
            f"a suite leaderboard's goes between {LEADERBOARD_START} markers "
            f"(README.md: `oodrl readme-table {LEADERBOARD}`)"
            if start == START
            else f"a pipeline's headline.md goes between {START} markers "
            "(`oodrl readme-table --readme docs/getting-started.md`)"
        )
        raise StoreError(f"{readme}: no {start} ... {END} markers to replace; {other}.")
    before, rest = text.split(start, 1)
    after = rest.split(END, 1)[1]
    atomic_write_text(readme, f"{before}{start}\n{block}\n{END}{after}")
