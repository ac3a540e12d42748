"""What the policy readers, converters and trainer lookup refuse, each in one line, and the small
normal paths beside those refusals (an oodrl checkpoint imported by `oodrl new`, per-row noise)."""

from __future__ import annotations

import hashlib
import pickle
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from test_load import observations, save_checkpoint, write_zip
from torch import nn

from oodrl.errors import ConfigError, PolicyError
from oodrl.policies.act import policy_from_checkpoint
from oodrl.policies.convert import (
    convert_checkpoint,
    convert_sb3,
    find_source,
    normalization,
    read_zoo_config,
    sb3_network,
)
from oodrl.policies.evaluate import evaluate_policy
from oodrl.policies.load import Sb3Policy, _sb3_algorithm, callable_spec, load_policy
from oodrl.policies.networks import NoisyQNetwork
from oodrl.policies.settings import ImportedConfig, SacConfig, TrainConfig
from oodrl.policies.trainers import trainer

#: The `data` entry of an SB3 zip whose policy class names DQN.
DQN_DATA = b'{"policy_class": {"__module__": "stable_baselines3.dqn.policies"}}'


@pytest.fixture
def sb3():
    return pytest.importorskip("stable_baselines3")


class SpacesEnv(gym.Env):
    """An environment of given spaces: SB3 and VecNormalize read its spaces and never step it."""

    def __init__(self, observation_space: gym.Space, action_space: gym.Space) -> None:
        self.observation_space = observation_space
        self.action_space = action_space

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, True, False, {}


def box(n: int) -> gym.spaces.Box:
    return gym.spaces.Box(-1.0, 1.0, (n,), np.float32)


def plain_state(*shapes: tuple[int, int]) -> dict[str, np.ndarray]:
    """`<i>.weight`/`<i>.bias` of Linear layers of the given (out, in) shapes."""
    rng = np.random.default_rng(0)
    state = {}
    for i, (n_out, n_in) in enumerate(shapes):
        state[f"{i}.weight"] = rng.standard_normal((n_out, n_in)).astype(np.float32)
        state[f"{i}.bias"] = rng.standard_normal(n_out).astype(np.float32)
    return state


# --- act: architectures and state_dicts that build no policy -----------------------------------


def test_an_unknown_mode_or_activation_is_refused_by_name():
    state = plain_state((3, 4))
    with pytest.raises(PolicyError, match="must be 'greedy' or 'noisy'; got 'eager'"):
        policy_from_checkpoint({"kind": "mlp"}, state, mode="eager")
    with pytest.raises(PolicyError, match="unknown activation 'gelu'; known: \\['relu', 'tanh'\\]"):
        policy_from_checkpoint({"kind": "mlp", "activation": "gelu"}, state)


def test_layers_that_do_not_chain_are_refused_with_both_sizes():
    with pytest.raises(PolicyError, match="a layer gives 5 outputs, the next takes 6 inputs"):
        policy_from_checkpoint({"kind": "mlp"}, plain_state((5, 4), (2, 6)))


def test_a_plain_state_dict_without_weights_or_a_bias_is_refused():
    with pytest.raises(PolicyError, match="no weight matrices"):
        policy_from_checkpoint({"kind": "mlp"}, {"0.bias": np.zeros(3, np.float32)})
    state = plain_state((3, 4))
    del state["0.bias"]
    with pytest.raises(PolicyError, match="no bias '0.bias' for a weight matrix"):
        policy_from_checkpoint({"kind": "mlp"}, state)


def test_a_noisy_state_dict_needs_every_mean_and_sigma(noisy_network: NoisyQNetwork):
    with pytest.raises(PolicyError, match="needs '\\*.weight_mu' entries"):
        policy_from_checkpoint({"kind": "noisy_dqn"}, plain_state((3, 4)))
    state = noisy_network.state_dict()
    del state["layers.1.bias_sigma"]
    with pytest.raises(PolicyError, match="lacks 'layers.1.bias_sigma'"):
        policy_from_checkpoint({"kind": "noisy_dqn"}, state)


# --- networks: the torch NoisyNet's per-row noise ----------------------------------------------


def test_torch_row_noise_is_the_numpy_policys_and_each_row_its_own(noisy_network: NoisyQNetwork):
    def rngs(start: int = 0, n: int = 6) -> list[np.random.Generator]:
        return [np.random.default_rng(start + i) for i in range(n)]

    obs = observations(6)
    x = torch.from_numpy(obs)
    with torch.no_grad():
        batched = noisy_network(x, noisy_network.row_noise(rngs())).numpy()
        alone = [
            noisy_network(x[i : i + 1], noisy_network.row_noise(rngs(i, 1)))[0] for i in range(6)
        ]
        mean = noisy_network(x).numpy()
    # Training draws its noise in torch and collection in numpy: the same generators must give
    # the same noisy outputs, or the noisy policy that was trained is not the one collected.
    numpy_policy = policy_from_checkpoint(
        {"kind": "noisy_dqn"}, noisy_network.state_dict(), mode="noisy"
    )
    np.testing.assert_allclose(numpy_policy.outputs(obs, rngs()), batched, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.stack([a.numpy() for a in alone]), batched, rtol=1e-6, atol=1e-6)
    assert not np.allclose(batched, mean)


def test_a_noisy_layer_describes_its_shape_and_noise_scale(noisy_network: NoisyQNetwork):
    assert "8 -> 32, sigma0=0.5" in repr(noisy_network.layers[0])


# --- trainers ----------------------------------------------------------------------------------


def test_each_training_settings_type_finds_its_trainer():
    from oodrl.policies.sac import train_sac
    from oodrl.policies.train import train

    assert trainer(TrainConfig()) is train
    assert trainer(SacConfig()) is train_sac


def test_an_imported_policy_or_unknown_settings_have_no_trainer():
    imported = ImportedConfig(env_id="CartPole-v1", source="RL Zoo folder", file="CartPole-v1.zip")
    with pytest.raises(
        PolicyError, match="imported \\(RL Zoo folder CartPole-v1.zip\\), not trained"
    ):
        trainer(imported)
    with pytest.raises(ConfigError, match="no trainer for dict"):
        trainer({"algorithm": "noisy_dqn"})


# --- load: files that are almost policies ------------------------------------------------------


def test_an_unknown_mode_is_refused_before_the_file_is_parsed(tmp_path: Path, noisy_network):
    path = save_checkpoint(tmp_path / "policy.pt", noisy_network)
    with pytest.raises(PolicyError, match="must be 'greedy' or 'noisy'; got 'eager'"):
        load_policy(path, mode="eager")


def test_a_file_that_only_starts_like_json_is_no_callable_pointer(tmp_path: Path):
    assert callable_spec(b"{not json") is None
    (tmp_path / "p.json").write_bytes(b"{not json")
    with pytest.raises(PolicyError, match="p.json is not a loadable policy file"):
        load_policy(tmp_path / "p.json")


def test_sb3_zips_are_told_apart_by_their_data_entry(tmp_path: Path):
    # A `data` entry that is JSON but no mapping is no SB3 model: the file is then a torch file.
    listed = write_zip(tmp_path / "list.zip", {"data": b"[1, 2]", "policy.pth": b""})
    assert _sb3_algorithm(listed.read_bytes()) is None
    with pytest.raises(PolicyError, match="not a loadable policy file"):
        load_policy(listed)
    # DQN's training settings name the algorithm when its policy class's module does not.
    data = b'{"policy_class": {"__module__": "elsewhere"}, "target_update_interval": 1000}'
    unnamed = write_zip(tmp_path / "dqn.zip", {"data": data, "policy.pth": b""})
    assert _sb3_algorithm(unnamed.read_bytes()) == "DQN"


def test_a_damaged_sb3_zip_is_refused_in_one_line(tmp_path: Path, sb3):
    path = write_zip(tmp_path / "model.zip", {"data": DQN_DATA, "policy.pth": b""})
    with pytest.raises(PolicyError, match="Stable-Baselines3 could not load it as DQN") as info:
        load_policy(path)
    assert "\n" not in str(info.value)


def test_an_sb3_zip_without_stable_baselines3_asks_to_install_it(tmp_path: Path, monkeypatch):
    path = write_zip(tmp_path / "model.zip", {"data": DQN_DATA, "policy.pth": b""})
    monkeypatch.setitem(sys.modules, "stable_baselines3", None)  # as if not installed
    with pytest.raises(PolicyError, match="Stable-Baselines3 DQN model; install stable-baselines3"):
        load_policy(path)


def test_a_continuous_sb3_model_acts_as_its_deterministic_predict(tmp_path: Path, sb3):
    model = sb3.PPO("MlpPolicy", "Pendulum-v1", seed=0, device="cpu")
    model.save(tmp_path / "ppo.zip")
    policy = load_policy(tmp_path / "ppo.zip", state_dim=3, action_size=1)
    assert (policy.kind, policy.action_kind) == ("sb3_ppo", "continuous")
    obs = np.random.default_rng(0).uniform(-1, 1, (16, 3)).astype(np.float32)
    actions = policy.act(obs)
    assert actions.dtype == np.float32 and actions.shape == (16, 1)
    np.testing.assert_array_equal(actions, model.predict(obs, deterministic=True)[0])


def test_an_sb3_model_of_neither_discrete_nor_box_actions_is_refused(sb3):
    env = SpacesEnv(box(4), gym.spaces.MultiDiscrete([2, 3]))
    model = sb3.PPO("MlpPolicy", env, seed=0, device="cpu")
    with pytest.raises(PolicyError, match="sb3_ppo model has action space MultiDiscrete"):
        Sb3Policy(model, kind="sb3_ppo", sha256="")
    with pytest.raises(PolicyError, match="SB3 PPO with action space MultiDiscrete"):
        sb3_network(model, "PPO")


# --- convert: networks oodrl has no architecture for -------------------------------------------


def test_an_activation_other_than_relu_or_tanh_is_refused(sb3):
    model = sb3.PPO(
        "MlpPolicy", "CartPole-v1", policy_kwargs={"activation_fn": nn.ELU}, seed=0, device="cpu"
    )
    with pytest.raises(PolicyError, match="PPO's actor has a ELU layer; oodrl converts Linear"):
        sb3_network(model, "PPO")


def test_a_network_mixing_activations_is_refused(sb3):
    model = sb3.DQN("MlpPolicy", "CartPole-v1", buffer_size=1000, seed=0, device="cpu")
    model.policy.q_net.q_net[1] = nn.Tanh()  # the other hidden layer keeps its ReLU
    with pytest.raises(PolicyError, match="DQN's q_net mixes activations \\['relu', 'tanh'\\]"):
        sb3_network(model, "DQN")


def test_a_features_extractor_other_than_flatten_is_refused(sb3):
    from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

    class Doubled(BaseFeaturesExtractor):
        def __init__(self, observation_space: gym.Space) -> None:
            super().__init__(observation_space, 2 * observation_space.shape[0])

        def forward(self, observations: torch.Tensor) -> torch.Tensor:
            return torch.cat([observations, observations], dim=1)

    kwargs = {"features_extractor_class": Doubled}
    model = sb3.PPO("MlpPolicy", "CartPole-v1", policy_kwargs=kwargs, seed=0, device="cpu")
    with pytest.raises(PolicyError, match="SB3 PPO uses Doubled; oodrl converts MlpPolicy"):
        sb3_network(model, "PPO")


def test_a_td3_actor_without_its_final_tanh_is_refused(sb3):
    model = sb3.TD3("MlpPolicy", "Pendulum-v1", buffer_size=1000, seed=0, device="cpu")
    model.policy.actor.mu = nn.Sequential(*list(model.policy.actor.mu)[:-1])
    with pytest.raises(PolicyError, match="TD3's actor does not end in tanh"):
        sb3_network(model, "TD3")


def test_an_algorithm_oodrl_has_no_network_for_is_refused_with_the_list(sb3):
    model = sb3.PPO("MlpPolicy", "CartPole-v1", seed=0, device="cpu")
    with pytest.raises(PolicyError, match="SB3 TRPO: oodrl converts A2C, DQN, PPO, SAC, TD3"):
        sb3_network(model, "TRPO")


# --- convert: VecNormalize files and RL Zoo configs --------------------------------------------


def vecnormalize(env: gym.Env, path: Path, **kwargs):
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    stats = VecNormalize(DummyVecEnv([lambda: env]), **kwargs)
    stats.save(path)
    return path


def test_a_file_that_is_no_vecnormalize_is_refused(tmp_path: Path):
    (tmp_path / "garbage.pkl").write_bytes(b"not a pickle")
    with pytest.raises(PolicyError, match="not a VecNormalize file \\(UnpicklingError\\)"):
        normalization(tmp_path / "garbage.pkl")
    (tmp_path / "dict.pkl").write_bytes(pickle.dumps({"mean": [0.0]}))
    with pytest.raises(PolicyError, match="not a VecNormalize file \\(no observation statistics"):
        normalization(tmp_path / "dict.pkl")


def test_vecnormalize_of_rewards_alone_applies_nothing_to_observations(tmp_path: Path, sb3):
    rewards = vecnormalize(SpacesEnv(box(3), box(1)), tmp_path / "rewards.pkl", norm_obs=False)
    assert normalization(rewards) is None


def test_vecnormalize_of_a_dict_observation_is_refused(tmp_path: Path, sb3):
    space = gym.spaces.Dict({"a": box(2), "b": box(3)})
    nested = vecnormalize(SpacesEnv(space, box(1)), tmp_path / "dict.pkl")
    with pytest.raises(PolicyError, match="normalises a Dict observation; oodrl needs a flat Box"):
        normalization(nested)


def test_statistics_of_other_observations_than_the_models_are_refused(tmp_path: Path, sb3):
    sb3.PPO("MlpPolicy", "CartPole-v1", seed=0, device="cpu").save(tmp_path / "model.zip")
    vecnormalize(SpacesEnv(box(3), box(1)), tmp_path / "vecnormalize.pkl")
    with pytest.raises(PolicyError, match="statistics of 3-dim observations; the model takes 4"):
        convert_sb3(find_source(tmp_path / "model.zip"), "CartPole-v1", tmp_path / "p.pt",
                    tmp_path / "p.json")  # fmt: skip
    assert not (tmp_path / "p.pt").exists()


def rl_zoo_run(root: Path, config: str) -> Path:
    """rl-zoo3's logs/<algo>/<env>_1/ with its config.yml; the settings are refused before the
    zip is read, so it need not hold a model."""
    run = root / "CartPole-v1_1"
    (run / "CartPole-v1").mkdir(parents=True)
    (run / "CartPole-v1.zip").write_bytes(b"")
    (run / "CartPole-v1" / "config.yml").write_text(config)
    return run


def test_rl_zoo_runs_with_stacked_frames_or_another_policy_are_refused(tmp_path: Path):
    with pytest.raises(PolicyError, match="frame_stack is not supported"):
        find_source(rl_zoo_run(tmp_path / "stacked", "frame_stack: 4\n"))
    with pytest.raises(PolicyError, match="policy 'CnnPolicy'; oodrl converts MlpPolicy"):
        find_source(rl_zoo_run(tmp_path / "cnn", "policy: CnnPolicy\n"))


def test_a_config_yml_that_is_no_mapping_or_would_run_code_is_refused(tmp_path: Path, monkeypatch):
    path = tmp_path / "config.yml"
    path.write_text("- policy\n- MlpPolicy\n")
    with pytest.raises(PolicyError, match="not an RL Zoo config.yml \\(expected a mapping\\)"):
        read_zoo_config(path)
    path.write_text("policy: [MlpPolicy\n")
    with pytest.raises(PolicyError, match="not an RL Zoo config.yml \\(ParserError\\)"):
        read_zoo_config(path)
    # Only RL Zoo's OrderedDict tag is constructed: any other Python tag is refused, not run.
    path.write_text("!!python/object/apply:os.system ['touch ran']\n")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(PolicyError, match="not an RL Zoo config.yml \\(ConstructorError\\)"):
        read_zoo_config(path)
    assert not (tmp_path / "ran").exists()


# --- convert: oodrl checkpoints made elsewhere -------------------------------------------------


def test_a_file_neither_torch_nor_an_oodrl_checkpoint_is_refused_in_one_line(tmp_path: Path):
    foreign = tmp_path / "foreign.pt"
    foreign.write_bytes(b"not a policy\n")
    plain = tmp_path / "plain.pt"
    torch.save(NoisyQNetwork(8, 4, (4,)).state_dict(), plain)  # weights, but no checkpoint
    for path, match in ((foreign, "Stable-Baselines3 .zip or an RL Zoo folder \\(torch.load: "),
                        (plain, "not an oodrl checkpoint, a Stable-Baselines3")):  # fmt: skip
        with pytest.raises(PolicyError, match=match) as info:
            convert_checkpoint(path, "LunarLander-v3", tmp_path / "p.pt", tmp_path / "p.json",
                               episodes=1, seed=0)  # fmt: skip
        assert "\n" not in str(info.value)
        assert not (tmp_path / "p.pt").exists()


def test_oodrl_new_imports_an_oodrl_checkpoint_as_it_acts(tmp_path: Path, noisy_network):
    from oodrl.suite.new import EVALUATION_SEED, _make_policy

    given = save_checkpoint(tmp_path / "given.pt", noisy_network)
    models = tmp_path / "models"
    models.mkdir()
    report = _make_policy(str(given), None, "LunarLander-v3", models, steps=0, episodes=2, seed=0)
    assert report["train_config"] == {
        "env_id": "LunarLander-v3",
        "source": "oodrl checkpoint",
        "file": "given.pt",
        "sha256": hashlib.sha256(given.read_bytes()).hexdigest(),
    }
    assert report["trainer"] == {"algorithm": "imported"} and report["steps_run"] == 0
    imported = load_policy(models / "policy.pt", state_dim=8, action_size=4)
    obs = observations()
    np.testing.assert_array_equal(imported.act(obs), load_policy(given).act(obs))
    returns = evaluate_policy(imported, 2, EVALUATION_SEED, env_id="LunarLander-v3")
    assert report["evaluation"]["returns"] == returns.tolist()
    assert report["evaluation"]["seeds"] == [EVALUATION_SEED, EVALUATION_SEED + 1]
