"""The stable command-line verbs (SPEC §10)."""

from __future__ import annotations

import subprocess
import sys

import pytest
import yaml
from typer.testing import CliRunner

from oodrl.cli import app

runner = CliRunner()


def test_list_shows_every_component_kind():
    result = runner.invoke(app, ["list"])
    assert result.exit_code == 0, result.output
    sections = {}
    current = None
    for line in result.output.splitlines():
        if not line.startswith(" "):
            current = line.rstrip(":")
            sections[current] = []
        else:
            sections[current].append(line.split()[0])
    # The paper's eight (SPEC §5), then SPEC §20's: four on the policy view, fqe_td, riqn,
    # conformal_martingale, deedee and random_scores.
    assert len(sections["detectors"]) == 19
    assert len(sections["injectors"]) == 14  # the nine of SPEC §4 and five live observation faults
    assert {"matched_auroc", "vus_pr"} <= set(sections["metrics"])
    assert "LunarLander-v3" in sections["environments"]  # the suite adds more (SPEC §11)
    # Online: four of SPEC §4 and the five live observation faults.
    assert result.output.count("(online)") == 9 and result.output.count("(posthoc)") == 5


def test_show_refuses_a_foreign_file_with_one_line(tmp_path):
    foreign = tmp_path / "foreign.yaml"
    foreign.write_text(yaml.safe_dump({"something": 1}))
    result = runner.invoke(app, ["show", str(foreign)])
    assert result.exit_code == 1
    assert result.output.count("\n") == 1 and str(foreign) in result.output


def test_evaluate_policy_rejects_an_unknown_mode(tmp_path):
    result = runner.invoke(app, ["evaluate-policy", "--mode", "eps", "--episodes", "1"])
    assert result.exit_code == 2
    assert "--mode must be 'greedy' or 'noisy'" in result.output


def test_stage_verbs_refuse_unlisted_components(repo_root):
    result = runner.invoke(
        app, ["fit", "kde_densty", "--id", "x.zarr", "--out", "y.pkl",
              "--params", str(repo_root / "params.yaml")],
    )  # fmt: skip
    assert result.exit_code == 2
    assert "'kde_densty' is not listed in benchmark.detectors." in result.output
    assert "Did you mean 'kde_density'?" in result.output


@pytest.mark.parametrize(
    ("sets", "given"),
    [
        ([], "got none."),
        (["--injector", "stuck_actuator", "--eval", "e.zarr"], "got --eval with --injector."),
        (["--injector", "stuck_actuator", "--id", "i.zarr"], "got --id with --injector."),
        (["--eval", "e.zarr", "--sweep", "sweep"], "got --eval, --sweep."),
    ],
)
def test_score_refuses_sets_that_are_not_one_stage_in_one_line(tmp_path, sets, given):
    """A clean stage's sets (--id with --eval, --calibration, --audit, --twins) or the
    injectors' (--ood, --sweep, --tiers)."""
    args = ["score", "mahalanobis_distance", "--model", "m.pkl", "--scores", "scores", *sets,
            "--params", str(_score_params(tmp_path))]  # fmt: skip
    result = runner.invoke(app, args)
    assert result.exit_code == 2
    assert (
        "score needs --id (ID set) with any of --eval (clean set), --calibration, --audit and "
        "--twins" in result.output
    )
    assert given in result.output and result.output.count("\n") == 1


def _score_params(folder):
    """A params file listing mahalanobis_distance, whatever the repository's lists."""
    path = folder / "params.yaml"
    path.write_text(yaml.safe_dump({
        "benchmark": {"detectors": ["mahalanobis_distance"], "injectors": ["stuck_actuator"]},
        "detectors": {"mahalanobis_distance": {"features": "state", "ridge": 0.001,
                                               "threshold_rule": "percentile",
                                               "threshold_percentile": 99.0, "seed": 0}},
        "anomaly": {"injectors": {"stuck_actuator": {}}},
    }))  # fmt: skip
    return path


def _clean_set(n: int, T: int, seed: int):  # noqa: N803 - the protocol's name for the horizon
    """n clean streams of T steps of a 3-dimensional state (a stored trajectory set)."""
    import numpy as np

    from oodrl.core.trajectory import TrajectorySet

    rng = np.random.default_rng(seed)
    states = rng.standard_normal((n, T + 1, 3)).astype(np.float32)
    actions = rng.integers(0, 2, size=(n, T))
    return TrajectorySet(
        states=states[:, :-1], actions=actions, rewards=np.ones((n, T), np.float32),
        next_states=states[:, 1:], dones=np.zeros((n, T), bool), executed_actions=actions,
        episode_index=np.zeros((n, T), np.int64), seeds=np.arange(n, dtype=np.int64) + seed,
        attrs={"T": T},
    )  # fmt: skip


def test_score_of_the_clean_sets_needs_and_scores_the_id_set(tmp_path, monkeypatch):
    """SPEC §24: the clean stage scores the ID set (`data/id.zarr`, every stream) into
    `scores/<detector>/id.zarr`, the clean group as the held-out sets', for the time-aware
    rule's standardiser; without --id it refuses in one line, before scoring anything."""
    from oodrl.config import load_params
    from oodrl.io.layout import CLEAN_GROUP, id_score_store, score_store
    from oodrl.io.store import read_scores, save_detector, write_trajectories
    from oodrl.protocol.scoring import score_set

    monkeypatch.chdir(tmp_path)  # the stage's timings land in ./.oodrl
    params = _score_params(tmp_path)
    name = "mahalanobis_distance"
    id_set, eval_set = _clean_set(6, 40, 0), _clean_set(3, 40, 100)
    write_trajectories(tmp_path / "id.zarr", id_set)
    write_trajectories(tmp_path / "eval.zarr", eval_set)
    detector = load_params(params, components=False).detector(name)
    detector.fit(id_set.trajectories())
    detector.calibrate(id_set.trajectories())
    save_detector(tmp_path / "m.pkl", detector, name, {})
    base = ["score", name, "--model", "m.pkl", "--scores", "scores", "--params", str(params)]
    refused = runner.invoke(app, [*base, "--eval", "eval.zarr"])
    assert refused.exit_code == 2 and refused.output.count("\n") == 1
    assert "score of the clean sets needs --id (the ID set, data/id.zarr)" in refused.output
    assert not (tmp_path / "scores").exists()
    result = runner.invoke(app, [*base, "--id", "id.zarr", "--eval", "eval.zarr"])
    assert result.exit_code == 0, result.output
    groups, _ = read_scores(id_score_store(tmp_path / "scores", name))
    assert id_score_store(tmp_path / "scores", name) == tmp_path / "scores" / name / "id.zarr"
    expected = score_set(detector, name, id_set, "the ID set")
    assert list(groups) == [CLEAN_GROUP]
    assert groups[CLEAN_GROUP]["scores"].tobytes() == expected.tobytes()
    assert groups[CLEAN_GROUP]["scores"].shape == (6, 40)  # every stream of the ID set
    assert score_store(tmp_path / "scores", name).is_file()


def test_train_policy_never_trains_unasked(tmp_path, repo_root, monkeypatch):
    """Without OODRL_RETRAIN_POLICY=1 a missing policy stops the stage with the commands that
    restore it or retrain it, in one line, instead of 13 minutes of training."""
    monkeypatch.delenv("OODRL_RETRAIN_POLICY", raising=False)
    out, report = tmp_path / "policy.pt", tmp_path / "policy.json"
    args = ["train-policy", "--out", str(out), "--report", str(report),
            "--params", str(repo_root / "params.yaml")]  # fmt: skip
    result = runner.invoke(app, args)
    assert result.exit_code == 1, result.output
    assert result.output.count("\n") == 1
    assert f"`git checkout -- {out} {report}`" in result.output
    assert "`OODRL_RETRAIN_POLICY=1 dvc repro -s -f train_policy`" in result.output
    assert not out.exists() and not report.exists()


def test_train_policy_keeps_a_policy_trained_with_these_settings(tmp_path, repo_root):
    out, report = tmp_path / "policy.pt", tmp_path / "policy.json"
    out.write_bytes((repo_root / "models/policy.pt").read_bytes())
    report.write_text((repo_root / "models/policy.json").read_text())
    args = ["train-policy", "--out", str(out), "--report", str(report),
            "--params", str(repo_root / "params.yaml")]  # fmt: skip
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert out.read_bytes() == (repo_root / "models/policy.pt").read_bytes()

    edited = yaml.safe_load((repo_root / "params.yaml").read_text())
    edited["policy"]["train"]["total_steps"] = 1000
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(edited))
    result = runner.invoke(app, [*args[:-1], str(tmp_path / "params.yaml")])
    assert result.exit_code == 2
    assert "policy.train.total_steps: 1000, but" in result.output


def test_pipeline_check_refuses_a_stale_dvc_yaml_in_one_line(tmp_path, repo_root, monkeypatch):
    (tmp_path / "src").symlink_to(repo_root / "src")
    (tmp_path / "params.yaml").write_text((repo_root / "params.yaml").read_text())
    monkeypatch.chdir(tmp_path)
    assert runner.invoke(app, ["pipeline", "write"]).exit_code == 0
    kde = tmp_path / "detectors/kde_density/dvc.yaml"
    pipeline = yaml.safe_load(kde.read_text())
    pipeline["stages"]["fit"]["deps"].remove("data/code/fit-kde_density.txt")
    kde.write_text(yaml.safe_dump(pipeline))
    result = runner.invoke(app, ["pipeline", "check"])
    assert result.exit_code == 2
    assert result.output.count("\n") == 1
    assert "detectors/kde_density/dvc.yaml is not what the template" in result.output
    assert "`oodrl pipeline write`" in result.output
    assert runner.invoke(app, ["pipeline", "write"]).exit_code == 0
    assert runner.invoke(app, ["pipeline", "check"]).exit_code == 0


@pytest.mark.parametrize(
    "module", ["oodrl.detectors.kde", "oodrl.detectors.mahalanobis", "oodrl.stages.collect"]
)
def test_numpy_stages_never_import_torch(module):
    code = f"import sys, {module}; assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_help_lists_the_stage_verbs_apart_from_the_commands_a_person_types(repo_root):
    """`oodrl --help` has one panel of the verbs the pipelines' DVC files call and lists every
    other command under Commands (a stage verb keeps its name: the dvc.yaml files call it).
    `check-params` is both, and listed as a person's: one runs it before `dvc repro`."""
    from oodrl.cli import STAGES_PANEL

    def commands(node) -> list[str]:
        if isinstance(node, dict):
            found = [node["cmd"]] if isinstance(node.get("cmd"), str) else []
            return found + [c for value in node.values() for c in commands(value)]
        return [c for value in node for c in commands(value)] if isinstance(node, list) else []

    files = [*repo_root.glob("**/dvc.yaml"), *(repo_root / "src/oodrl/suite").glob("*.yaml")]
    called = {
        command.split()[1]
        for path in files
        if ".dvc" not in path.parts
        for command in commands(yaml.safe_load(path.read_text()))
    }
    assert called >= {"check-params", "collect-id", "fit", "score", "leaderboard", "import-dataset"}
    panels = {info.name: info.rich_help_panel for info in app.registered_commands}
    assert {name for name, panel in panels.items() if panel == STAGES_PANEL} == called - {
        "check-params"
    }
    result = runner.invoke(app, ["--help"], env={"COLUMNS": "100"})
    assert result.exit_code == 0, result.output
    people, stages = result.output.split(STAGES_PANEL)
    assert "check-params" in people and "suite" in people and "collect-id" not in people
    assert "collect-id" in stages and "check-params" not in stages
