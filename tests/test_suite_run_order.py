"""`oodrl suite run` submits the pipelines longest first, by their last build's stage wall time."""

from __future__ import annotations

from pathlib import Path

from oodrl.suite.run import _longest_first


def _built(root: Path, pipeline: str, seconds: float) -> None:
    reports = root / pipeline / "reports"
    reports.mkdir(parents=True)
    (reports / "run_meta.yaml").write_text(f"stage_wall_s: {{}}\ntotal_stage_wall_s: {seconds}\n")


def test_longest_last_build_first_and_never_built_before_all(tmp_path):
    _built(tmp_path, ".", 742.4)
    _built(tmp_path, "pipeline/half_cheetah", 3225.3)
    _built(tmp_path, "pipeline/cartpole", 930.1)
    suite = [".", "pipeline/cartpole", "pipeline/half_cheetah", "pipeline/hopper_policy1"]
    assert _longest_first(tmp_path, suite) == [
        "pipeline/hopper_policy1",  # never built here: its time is unknown, so it goes first
        "pipeline/half_cheetah",
        "pipeline/cartpole",
        ".",
    ]
