"""The leaderboard on the results files a real (tiny) pipeline writes."""

from __future__ import annotations

from pathlib import Path

from conftest import DETECTORS, INJECTORS

from oodrl.io import yamlio
from oodrl.metrics.tier_results import TIER_RESULTS
from oodrl.stages.leaderboard import run_leaderboard


def test_leaderboard_reads_the_pipelines_results(built_repo: Path, tmp_path: Path):
    results = built_repo / "reports" / "results.yaml"
    board = run_leaderboard({"LunarLander-v3": results}, tmp_path / "headline", 50, 0.95, 0)
    lead = board.overall[board.lead]
    assert board.lead == ("matched_auroc", "headline")
    assert sorted(lead.detectors) == sorted(DETECTORS)
    assert lead.tasks == tuple(("LunarLander-v3", f, "headline") for f in sorted(INJECTORS))
    assert lead.bootstrap == "episodes"
    document = yamlio.load((tmp_path / "headline" / "leaderboard.yaml").read_text())
    assert document["protocol_version"] == yamlio.load(results.read_text()).get(
        "protocol_version", 1
    )
    tiers = built_repo / TIER_RESULTS
    if tiers.is_file():  # the pipeline scores the impact tiers: they lead, harmful ones first
        from oodrl.metrics.leaderboard import tier_order

        board = run_leaderboard({"LunarLander-v3": tiers}, tmp_path / "tiers", 50, 0.95, 0)
        # Which tiers the tiny search reaches and verifies varies; the order never does.
        assert list(board.tiers) == tier_order(board.tiers)
        assert board.lead[0].startswith("detection_rate@") and board.lead[1] == board.tiers[0]
