import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from oodrl.policies.load import load_policy
from oodrl.policies.train import TrainConfig, train

TINY = TrainConfig(
    hidden_sizes=(32, 32),
    total_steps=600,
    learning_starts=200,
    train_freq=2,
    target_sync=100,
    eval_every=200,
    eval_episodes=2,
    early_stop_return=1e9,
    final_eval_episodes=2,
    seed=3,
)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict]:
    folder = tmp_path_factory.mktemp("train")
    report = train(TINY, folder / "policy.pt", folder / "policy.json", progress=False)
    return folder / "policy.pt", folder / "policy.json", report


@pytest.mark.slow
def test_smoke_training_writes_a_loadable_checkpoint_and_report(tiny_run):
    policy_path, report_path, report = tiny_run
    checkpoint = torch.load(policy_path, weights_only=True)
    assert checkpoint["format"] == "oodrl-policy"
    assert checkpoint["version"] == 1
    assert checkpoint["architecture"] == {
        "kind": "noisy_dqn",
        "state_dim": 8,
        "n_actions": 4,
        "hidden_sizes": [32, 32],
        "sigma0": 0.5,
    }
    assert not list(policy_path.parent.glob("*.tmp"))

    text = report_path.read_text()
    on_disk = json.loads(text)
    assert text == json.dumps(on_disk, indent=2, sort_keys=True) + "\n"
    evaluation = on_disk["evaluation"]
    assert evaluation["seeds"] == [1_000_000, 1_000_001]
    assert evaluation["mean"] == pytest.approx(np.mean(evaluation["returns"]))
    assert evaluation["min"] <= evaluation["mean"] <= evaluation["max"]
    assert [s for s, _ in on_disk["learning_curve"]] == [400, 600]
    assert on_disk["best_step"] in (400, 600)
    assert on_disk["steps_run"] == 600
    assert {"oodrl", "torch", "gymnasium", "numpy"} <= set(on_disk["versions"])
    assert on_disk["train_config"] == TINY.as_dict()
    assert report["evaluation"] == evaluation

    policy = load_policy(policy_path)
    assert (policy.state_dim, policy.action_size, policy.kind) == (8, 4, "noisy_dqn")


@pytest.mark.slow
def test_training_is_byte_reproducible(tiny_run, tmp_path: Path):
    policy_path, _, report = tiny_run
    again = train(TINY, tmp_path / "policy.pt", tmp_path / "policy.json", progress=False)
    assert (tmp_path / "policy.pt").read_bytes() == policy_path.read_bytes()
    assert again["evaluation"] == report["evaluation"]
    assert again["learning_curve"] == report["learning_curve"]


@pytest.mark.slow
def test_training_stops_at_the_first_evaluation_good_enough_and_prints_it(tmp_path, capsys):
    config = dataclasses.replace(TINY, early_stop_return=-1e9)
    report = train(config, tmp_path / "policy.pt", tmp_path / "policy.json", progress=True)
    assert report["steps_run"] == 400 and report["best_step"] == 400
    assert [s for s, _ in report["learning_curve"]] == [400]
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 1 and lines[0].startswith("step      400  eval")


def test_config_normalises_hidden_sizes_for_the_report():
    config = TrainConfig(hidden_sizes=[64, 64])
    assert config.hidden_sizes == (64, 64)
    assert config.as_dict()["hidden_sizes"] == [64, 64]


@pytest.mark.slow
def test_sac_smoke_training_exports_an_actor_that_acts_like_sb3(tmp_path: Path):
    """A tiny SAC run: its exported actor (numpy, torch-free acting) matches SB3's own actions."""
    from stable_baselines3 import SAC

    from oodrl.policies.act import policy_from_checkpoint
    from oodrl.policies.sac import actor_state_dict, train_sac
    from oodrl.policies.settings import SacConfig

    config = SacConfig(
        env_id="Pendulum-v1", total_steps=400, learning_starts=100, eval_every=200,
        eval_episodes=1, final_eval_episodes=2, early_stop_return=1e9,
    )  # fmt: skip
    report = train_sac(config, tmp_path / "policy.pt", tmp_path / "policy.json")
    assert [s for s, _ in report["learning_curve"]] == [200, 400]
    assert report["trainer"]["algorithm"] == "SAC"
    policy = load_policy(tmp_path / "policy.pt")
    assert (policy.kind, policy.action_kind, policy.action_size) == ("tanh_actor", "continuous", 1)
    assert json.loads((tmp_path / "policy.json").read_text())["evaluation"]["episodes"] == 2

    model = SAC("MlpPolicy", "Pendulum-v1", seed=3, device="cpu")
    exported = policy_from_checkpoint(
        {"kind": "tanh_actor", "action_low": [-2.0], "action_high": [2.0]},
        actor_state_dict(model),
    )
    obs = np.random.default_rng(0).uniform(-1, 1, (64, 3)).astype(np.float32)
    expected, _ = model.predict(obs, deterministic=True)
    actions = exported.act(obs)
    assert actions.dtype == np.float32 and actions.shape == (64, 1)
    np.testing.assert_allclose(actions, expected, atol=1e-5)


@pytest.mark.slow
def test_sac_training_resumes_from_its_last_evaluation(tmp_path: Path, monkeypatch):
    """Interrupted after its second evaluation, a SAC training goes on from there when started
    again with the same settings; resuming the same checkpoint twice trains the same actor."""
    import shutil

    from oodrl.policies.sac import TrainingCheckpoint, train_sac
    from oodrl.policies.settings import SacConfig

    config = SacConfig(
        env_id="Pendulum-v1", total_steps=600, learning_starts=100, eval_every=200,
        eval_episodes=1, final_eval_episodes=1, early_stop_return=1e9,
    )  # fmt: skip
    save = TrainingCheckpoint.save

    def save_then_stop(self, model, progress):
        save(self, model, progress)
        if progress["step"] == 400:
            raise KeyboardInterrupt

    monkeypatch.setattr(TrainingCheckpoint, "save", save_then_stop)
    first, second = tmp_path / "a", tmp_path / "b"
    first.mkdir()
    with pytest.raises(KeyboardInterrupt):
        train_sac(config, first / "policy.pt", first / "policy.json")
    assert not (first / "policy.pt").exists()
    shutil.copytree(first / "policy.pt.training", second / "policy.pt.training")
    monkeypatch.setattr(TrainingCheckpoint, "save", save)

    reports = [train_sac(config, d / "policy.pt", d / "policy.json") for d in (first, second)]
    for directory, report in zip((first, second), reports, strict=True):
        assert report["trainer"]["resumed_at_steps"] == [400]
        assert [s for s, _ in report["learning_curve"]] == [200, 400, 600]
        assert report["steps_run"] == 600
        assert not (directory / "policy.pt.training").exists()
    assert (first / "policy.pt").read_bytes() == (second / "policy.pt").read_bytes()
