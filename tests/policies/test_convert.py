"""SB3 models and RL Zoo folders become oodrl checkpoints that act as SB3's predict (SPEC §18).

Each model is trained here for a few hundred steps on an environment outside the suite, with
VecNormalize, so its weights and statistics are not their initial values; the converted policy
must pick SB3's deterministic action on 2,000 observations, up to the documented rounding.
"""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path

import numpy as np
import pytest
import yaml

from oodrl.errors import PolicyError
from oodrl.policies.convert import (
    ACTION_TOLERANCE,
    ARGMAX_MARGIN,
    convert_sb3,
    find_source,
    read_zoo_config,
)
from oodrl.policies.load import load_policy

sb3 = pytest.importorskip("stable_baselines3")

#: algorithm, environment (outside the suite), training steps, algorithm settings.
MODELS = [
    ("PPO", "MountainCar-v0", 512, {"n_steps": 256, "batch_size": 64, "n_epochs": 2}),
    ("PPO", "InvertedPendulum-v5", 512, {"n_steps": 256, "batch_size": 64, "n_epochs": 2}),
    ("A2C", "MountainCarContinuous-v0", 400, {}),
    ("DQN", "MountainCar-v0", 600, {"learning_starts": 100, "buffer_size": 1000}),
    ("SAC", "MountainCarContinuous-v0", 250, {"learning_starts": 100, "buffer_size": 1000}),
    ("TD3", "InvertedPendulum-v5", 250, {"learning_starts": 100, "buffer_size": 1000}),
]


def train(algorithm: str, env_id: str, steps: int, settings: dict, folder: Path):
    """An SB3 model trained under VecNormalize, saved as model.zip + vecnormalize.pkl."""
    import gymnasium as gym
    import torch
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    torch.set_num_threads(1)
    venv = VecNormalize(DummyVecEnv([lambda: gym.make(env_id)]), norm_reward=False)
    model = getattr(sb3, algorithm)("MlpPolicy", venv, seed=0, device="cpu", **settings)
    model.learn(steps)
    folder.mkdir(parents=True, exist_ok=True)
    model.save(folder / "model.zip")
    venv.save(folder / "vecnormalize.pkl")
    return model, venv


def observations(space, n: int = 2000) -> np.ndarray:
    """n observations spread over the space (±3 where it is unbounded), float32 as collected."""
    low = np.where(np.isfinite(space.low), space.low, -3.0)
    high = np.where(np.isfinite(space.high), space.high, 3.0)
    return np.random.default_rng(0).uniform(low, high, (n, space.shape[0])).astype(np.float32)


def assert_acts_as_sb3(policy, model, venv) -> None:
    obs = observations(venv.observation_space)
    expected, _ = model.predict(venv.normalize_obs(obs), deterministic=True)
    actions = policy.act(obs, None)
    if policy.action_kind == "discrete":
        outputs = np.sort(policy.outputs(obs), axis=1)
        near_tie = outputs[:, -1] - outputs[:, -2] <= ARGMAX_MARGIN
        assert np.array_equal(actions[~near_tie], expected[~near_tie])
        assert near_tie.mean() < 0.01
    else:
        span = model.action_space.high - model.action_space.low
        assert (np.abs(actions - expected) <= ACTION_TOLERANCE * span).all()


@pytest.mark.slow
@pytest.mark.parametrize(
    ("algorithm", "env_id", "steps", "settings"), MODELS, ids=[f"{m[0]}-{m[1]}" for m in MODELS]
)
def test_converted_sb3_model_picks_sb3s_deterministic_action(
    tmp_path: Path, algorithm, env_id, steps, settings
):
    model, venv = train(algorithm, env_id, steps, settings, tmp_path / "run")
    report = convert_sb3(
        find_source(tmp_path / "run" / "model.zip"),
        env_id,
        tmp_path / "policy.pt",
        tmp_path / "policy.json",
        episodes=1,
    )
    assert report["train_config"]["source"] == f"Stable-Baselines3 {algorithm} .zip"
    assert report["env_id"] == env_id and report["evaluation"]["episodes"] == 1
    policy = load_policy(tmp_path / "policy.pt")
    assert policy.normalization is not None  # vecnormalize.pkl beside the zip was found
    assert_acts_as_sb3(policy, model, venv)
    # The statistics matter: without them the same network acts otherwise.
    policy.normalization = None
    obs = observations(venv.observation_space, 200)
    assert not np.array_equal(policy.act(obs, None), model.predict(venv.normalize_obs(obs))[0])


def rl_zoo_folder(root: Path, env_id: str, config: dict) -> Path:
    """The layout rl-zoo3 writes: logs/<algo>/<env>_1/{<env>.zip, <env>/config.yml, ...}."""
    model, venv = train("PPO", env_id, 256, {"n_steps": 128, "batch_size": 64}, root / "tmp")
    run = root / "logs" / "ppo" / f"{env_id}_1"
    (run / env_id).mkdir(parents=True)
    model.save(run / f"{env_id}.zip")
    model.save(run / "best_model.zip")
    venv.save(run / env_id / "vecnormalize.pkl")
    # rl-zoo3 dumps its hyperparameters as an OrderedDict with PyYAML's default dumper.
    (run / env_id / "config.yml").write_text(yaml.dump(OrderedDict(config)))
    return run, model, venv


@pytest.mark.slow
def test_rl_zoo_folder_converts_with_its_statistics(tmp_path: Path):
    env_id = "MountainCarContinuous-v0"
    settings = {"normalize": True, "n_timesteps": 256, "policy": "MlpPolicy"}
    run, model, venv = rl_zoo_folder(tmp_path, env_id, settings)
    assert read_zoo_config(run / env_id / "config.yml") == settings
    source = find_source(run)
    assert (source.model.name, source.env_id) == (f"{env_id}.zip", env_id)
    convert_sb3(source, env_id, tmp_path / "policy.pt", tmp_path / "policy.json", episodes=1)
    assert_acts_as_sb3(load_policy(tmp_path / "policy.pt"), model, venv)


@pytest.mark.slow
def test_rl_zoo_folder_with_an_env_wrapper_is_refused(tmp_path: Path):
    wrapper = "sb3_contrib.common.wrappers.TimeFeatureWrapper"
    run, *_ = rl_zoo_folder(tmp_path, "MountainCarContinuous-v0", {"env_wrapper": wrapper})
    with pytest.raises(PolicyError, match="env_wrapper") as info:
        find_source(run)
    assert "\n" not in str(info.value)


def test_a_folder_that_is_no_rl_zoo_run_is_refused(tmp_path: Path):
    (tmp_path / "model.zip").write_bytes(b"")
    with pytest.raises(PolicyError, match="not an RL Zoo run folder"):
        find_source(tmp_path)


def test_sde_and_foreign_files_are_refused_in_one_line(tmp_path: Path):
    model = sb3.SAC("MlpPolicy", "MountainCarContinuous-v0", use_sde=True, device="cpu")
    model.save(tmp_path / "sde.zip")
    foreign = tmp_path / "foreign.zip"
    foreign.write_bytes(b"not a zip")
    for path, match in ((tmp_path / "sde.zip", "use_sde"), (foreign, "not a Stable-Baselines3")):
        with pytest.raises(PolicyError, match=match) as info:
            convert_sb3(find_source(path), "MountainCarContinuous-v0", tmp_path / "p.pt",
                        tmp_path / "p.json")  # fmt: skip
        assert "\n" not in str(info.value)
        assert not (tmp_path / "p.pt").exists()


def test_training_leaves_no_log_folder_in_the_temporary_directory(tmp_path, monkeypatch):
    """SB3's quiet logger would make an empty `SB3-<date>` folder in the system's temporary
    directory per training (`oodrl new --train`, the SAC trainer); oodrl's makes none."""
    import tempfile

    from oodrl.policies.convert import train_sb3

    monkeypatch.delenv("SB3_LOGDIR", raising=False)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    train_sb3("ppo", "CartPole-v1", 128, 0, tmp_path / "model.zip")
    assert (tmp_path / "model.zip").is_file()
    assert not list((tmp_path / "tmp").glob("SB3-*"))
