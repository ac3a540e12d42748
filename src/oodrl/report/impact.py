"""The impact tiers as a reader sees them (SPEC §15): a markdown table of every fault's tiers and
a figure of the impact curves, drawn from an impact document (`oodrl.protocol.impact`). The
tier_metrics stage draws them; the impact stages only measure, so their code stamps leave the report
out."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from oodrl.protocol.impact import tier_severity


def impact_table(document: Mapping[str, Any]) -> str:
    """Markdown: per fault, the severity of each tier with R̃ re-measured there on fresh
    episodes [CI] and their number (✗ where that verification misses), or why it has none
    (unreachable, not reached); and R̃ at σ = max."""
    from oodrl.report.tables import markdown_table

    def cell(tier: Mapping[str, Any]) -> str:
        if tier_severity(tier) is None:
            return str(tier["severity"])
        check = tier["verification"]
        low, high = check["ci"]
        mark = "" if check["verified"] else " ✗ unverified"
        return (
            f"{tier['severity']:.4g} (R̃ {check['normalised']:.3f} [{low:.3f}, {high:.3f}], "
            f"n = {check['episodes']}{mark})"
        )

    names = list(document["levels"])
    rows = []
    for fault, record in sorted(document["faults"].items()):
        last = record["curve"][-1]
        steps = record.get("severity_steps")
        label = f"{fault} ({steps} steps)" if steps else fault
        rows.append(
            [label, *(cell(record["tiers"][n]) for n in names),
             f"{last['normalised']:.3f} (σ={last['severity']:g})"]
        )  # fmt: skip
    header = ["fault", *(f"{n} (R̃={document['levels'][n]:g})" for n in names), "R̃ at largest σ"]
    title = (
        f"Impact tiers, {document['env_id']}: the severity σ of each tier, found by a search "
        "that measures R̃ where it reports (SPEC §19), and R̃ re-measured there on n fresh "
        "episodes no probe used (95% bootstrap CI); ✗ marks a tier whose verification misses "
        "its level, left out of tier aggregates. A stepped fault takes a tier only at a step "
        "whose R̃ lands between the tier's level and the next one's (0.5 after severe)\n\n"
    )
    return title + markdown_table(header, rows) + "\n"


def plot_impact_curves(document: Mapping[str, Any], path: str | Path) -> Path:
    """One line per fault: R̃(σ) with its CI band (raw estimates as points, monotone fit as line),
    the tier levels as dashed lines."""
    from oodrl.report.plots import _colours, _figure, _save

    faults = sorted(document["faults"])
    colours = _colours(faults)
    figure = _figure(6.4, 4.2)
    axes = figure.subplots()
    for fault in faults:
        curve = document["faults"][fault]["curve"]
        xs = [0.0, *(p["severity"] for p in curve)]
        colour = colours[fault]
        axes.fill_between(xs, [1.0, *(p["ci"][0] for p in curve)],
                          [1.0, *(p["ci"][1] for p in curve)], color=colour, alpha=0.12,
                          linewidth=0)  # fmt: skip
        axes.plot(xs, [1.0, *(p["monotone"] for p in curve)], color=colour, label=fault)
        axes.plot(xs[1:], [p["normalised"] for p in curve], "o", markersize=3, color=colour)
    for name, level in document["levels"].items():
        axes.axhline(level, color="0.4", linestyle="--", linewidth=0.8)
        axes.annotate(name, (0.0, level), fontsize=7, color="0.3", va="bottom")
    axes.set_xlabel("severity σ", fontsize=8)
    axes.set_ylabel("normalised return R̃", fontsize=8)
    axes.set_title(f"Impact curves, {document['env_id']}", fontsize=9)
    axes.tick_params(labelsize=7)
    axes.grid(alpha=0.3, linewidth=0.5)
    axes.legend(fontsize=7, frameon=False)
    return _save(figure, path)
