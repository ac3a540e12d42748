import hashlib
import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from oodrl.errors import PolicyError
from oodrl.policies.evaluate import evaluate_policy
from oodrl.policies.load import load_policy
from oodrl.policies.networks import NoisyQNetwork, mlp, scale_noise

COMMITTED_POLICY = Path(__file__).resolve().parents[2] / "models" / "policy.pt"


def observations(n: int = 256, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, 8)).astype(np.float32)


def save_checkpoint(path: Path, network: NoisyQNetwork) -> Path:
    torch.save(
        {
            "format": "oodrl-policy",
            "version": 1,
            "architecture": {
                "kind": "noisy_dqn",
                "state_dim": network.state_dim,
                "n_actions": network.n_actions,
                "hidden_sizes": list(network.hidden_sizes),
                "sigma0": network.sigma0,
            },
            "state_dict": network.state_dict(),
        },
        path,
    )
    return path


@pytest.fixture
def checkpoint(tmp_path: Path, noisy_network: NoisyQNetwork) -> Path:
    return save_checkpoint(tmp_path / "policy.pt", noisy_network)


# --- networks ----------------------------------------------------------------------------------


def test_row_noise_equals_the_dense_factorised_weight(noisy_network: NoisyQNetwork):
    layer = noisy_network.layers[0]
    x = torch.from_numpy(observations(5))
    eps_in, eps_out = scale_noise(torch.randn(5, 8)), scale_noise(torch.randn(5, 32))
    batched = layer(x, (eps_in, eps_out))
    for i in range(5):
        weight = layer.weight_mu + layer.weight_sigma * torch.outer(eps_out[i], eps_in[i])
        bias = layer.bias_mu + layer.bias_sigma * eps_out[i]
        torch.testing.assert_close(batched[i], weight @ x[i] + bias)


def test_shared_noise_broadcasts_like_identical_rows(noisy_network: NoisyQNetwork):
    x = torch.from_numpy(observations(4))
    noise = noisy_network.sample_noise(torch.Generator().manual_seed(1))
    per_row = [(e_in.expand(4, -1), e_out.expand(4, -1)) for e_in, e_out in noise]
    torch.testing.assert_close(noisy_network(x, noise), noisy_network(x, per_row))


# --- oodrl checkpoints ---------------------------------------------------------------------------


def test_own_checkpoint_round_trips_greedy(checkpoint: Path, noisy_network: NoisyQNetwork):
    policy = load_policy(checkpoint)
    obs = observations()
    expected = noisy_network(torch.from_numpy(obs)).argmax(1).numpy()
    actions = policy.act(obs, None)
    assert actions.dtype == np.int64 and actions.shape == (len(obs),)
    np.testing.assert_array_equal(actions, expected)
    assert (policy.state_dim, policy.action_size, policy.mode) == (8, 4, "greedy")
    assert policy.sha256 == hashlib.sha256(checkpoint.read_bytes()).hexdigest()


def test_noisy_mode_is_reproducible_per_row_and_differs_from_greedy(checkpoint: Path):
    noisy = load_policy(checkpoint, mode="noisy")
    obs = observations()

    def rngs(n: int = len(obs), start: int = 0) -> list[np.random.Generator]:
        return [np.random.default_rng(start + i) for i in range(n)]

    first = noisy.act(obs, rngs())
    np.testing.assert_array_equal(first, noisy.act(obs, rngs()))
    # Row i depends only on rngs[i]: acting row by row gives the batched result.
    one_by_one = [noisy.act(obs[i : i + 1], rngs(1, i))[0] for i in range(len(obs))]
    np.testing.assert_array_equal(first, one_by_one)
    assert (first != load_policy(checkpoint).act(obs, None)).any()
    with pytest.raises(ValueError, match="one numpy Generator per"):
        noisy.act(obs, None)


def test_dimension_mismatch_is_a_policy_error(checkpoint: Path):
    with pytest.raises(PolicyError, match="8-dim observations"):
        load_policy(checkpoint, state_dim=6)
    with pytest.raises(PolicyError, match="4 actions"):
        load_policy(checkpoint, action_size=2)


def test_unknown_checkpoint_version_is_a_policy_error(tmp_path: Path, noisy_network):
    path = save_checkpoint(tmp_path / "p.pt", noisy_network)
    checkpoint = torch.load(path, weights_only=True)
    checkpoint["version"] = 99
    torch.save(checkpoint, path)
    with pytest.raises(PolicyError, match="version 99"):
        load_policy(path)


# --- plain state_dicts ---------------------------------------------------------------------------


class Wrapped(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.net = mlp(8, 4, (16, 16))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


@pytest.mark.parametrize("wrapper", ["sequential", "module_attribute", "nested_dict"])
def test_plain_mlp_state_dict_with_architecture(tmp_path: Path, wrapper: str):
    torch.manual_seed(1)
    module = Wrapped()
    state = module.net.state_dict() if wrapper == "sequential" else module.state_dict()
    torch.save({"state_dict": state} if wrapper == "nested_dict" else state, tmp_path / "m.pt")
    policy = load_policy(tmp_path / "m.pt", architecture={"kind": "mlp", "hidden_sizes": [16, 16]})
    obs = observations()
    np.testing.assert_array_equal(
        policy.act(obs, None), module(torch.from_numpy(obs)).argmax(1).numpy()
    )
    assert (policy.state_dim, policy.action_size, policy.kind) == (8, 4, "mlp")


def test_plain_noisy_state_dict_with_architecture(tmp_path: Path, noisy_network):
    torch.save(noisy_network.state_dict(), tmp_path / "n.pt")
    architecture = {"kind": "noisy_dqn", "hidden_sizes": [32, 32], "sigma0": 0.5}
    policy = load_policy(tmp_path / "n.pt", mode="noisy", architecture=architecture)
    rngs = [np.random.default_rng(i) for i in range(3)]
    assert policy.act(observations(3), rngs).shape == (3,)


def test_plain_state_dict_needs_an_architecture(tmp_path: Path):
    torch.save(mlp(8, 4).state_dict(), tmp_path / "m.pt")
    with pytest.raises(PolicyError, match="pass architecture="):
        load_policy(tmp_path / "m.pt")


def test_wrong_architecture_is_a_policy_error(tmp_path: Path):
    torch.save(mlp(8, 4, (16, 16)).state_dict(), tmp_path / "m.pt")
    with pytest.raises(PolicyError, match="do not fit architecture"):
        load_policy(tmp_path / "m.pt", architecture={"kind": "mlp", "hidden_sizes": [32]})
    with pytest.raises(PolicyError, match="unknown architecture kind 'cnn'"):
        load_policy(tmp_path / "m.pt", architecture={"kind": "cnn"})
    with pytest.raises(PolicyError, match="needs a noisy_dqn"):
        load_policy(
            tmp_path / "m.pt", mode="noisy", architecture={"kind": "mlp", "hidden_sizes": [16, 16]}
        )


# --- Stable-Baselines3 ---------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("algorithm", ["DQN", "PPO"])
def test_sb3_models_load_and_act_deterministically(tmp_path: Path, algorithm: str):
    sb3 = pytest.importorskip("stable_baselines3")
    import gymnasium as gym

    torch.set_num_threads(1)
    env = gym.make("LunarLander-v3")
    if algorithm == "DQN":
        model = sb3.DQN(
            "MlpPolicy", env, learning_starts=100, buffer_size=1000, seed=0, device="cpu"
        )
    else:
        model = sb3.PPO(
            "MlpPolicy", env, n_steps=64, batch_size=32, n_epochs=1, seed=0, device="cpu"
        )
    model.learn(200)
    model.save(tmp_path / "model.zip")

    policy = load_policy(tmp_path / "model.zip")
    assert policy.kind == f"sb3_{algorithm.lower()}"
    assert (policy.state_dim, policy.action_size) == (8, 4)
    obs = observations(64)
    expected, _ = model.predict(obs, deterministic=True)
    np.testing.assert_array_equal(policy.act(obs, None), expected)
    with pytest.raises(PolicyError, match="noisy"):
        load_policy(tmp_path / "model.zip", mode="noisy")

    # It works as the benchmark's policy: the collector rolls it out, reproducibly.
    from oodrl.envs.collect import collect
    from oodrl.envs.lunar_lander import LunarLanderAdapter

    first = collect(LunarLanderAdapter(), policy, [3, 4], 40)
    again = collect(LunarLanderAdapter(), load_policy(tmp_path / "model.zip"), [3, 4], 40)
    assert first.states.shape == (2, 40, 8)
    np.testing.assert_array_equal(first.actions, again.actions)
    np.testing.assert_array_equal(first.states, again.states)


# --- bad files -----------------------------------------------------------------------------------


def write_zip(path: Path, entries: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in entries.items():
            archive.writestr(name, data)
    return path


@pytest.mark.parametrize(
    "content",
    [
        b"",
        b"not a policy at all\n",
        bytes(range(256)) * 4,
        "truncated",
        "tensor",
        "foreign_zip",
        "other_sb3",
    ],
)
def test_corrupt_or_foreign_files_raise_a_one_line_policy_error(
    tmp_path: Path, checkpoint: Path, content
):
    path = tmp_path / "bad.pt"
    if content == "truncated":
        path.write_bytes(checkpoint.read_bytes()[:300])
    elif content == "tensor":
        torch.save(torch.zeros(3), path)
    elif content == "foreign_zip":
        write_zip(path, {"hello.txt": b"hi"})
    elif content == "other_sb3":
        write_zip(path, {"data": b'{"policy_class": {}, "gae_lambda": 0.95}', "policy.pth": b""})
    else:
        path.write_bytes(content)
    with pytest.raises(PolicyError) as info:
        load_policy(path)
    message = str(info.value)
    assert str(path) in message and "\n" not in message
    assert "accepted" in message or "architecture" in message


def test_missing_file_is_a_policy_error(tmp_path: Path):
    with pytest.raises(PolicyError, match="cannot read policy file"):
        load_policy(tmp_path / "nowhere.pt")


def test_pickled_modules_are_refused(tmp_path: Path):
    buffer = io.BytesIO()
    torch.save(mlp(8, 4), buffer)  # a whole pickled module, not weights: weights_only refuses it
    (tmp_path / "module.pt").write_bytes(buffer.getvalue())
    with pytest.raises(PolicyError, match="weights_only=True refuses"):
        load_policy(tmp_path / "module.pt", architecture={"kind": "mlp", "hidden_sizes": [64, 64]})


# --- evaluation ----------------------------------------------------------------------------------


def test_evaluate_policy_is_reproducible_in_both_modes(checkpoint: Path):
    greedy = load_policy(checkpoint)
    returns = evaluate_policy(greedy, episodes=2, seed=5)
    assert returns.shape == (2,) and np.isfinite(returns).all()
    np.testing.assert_array_equal(returns, evaluate_policy(greedy, episodes=2, seed=5))
    # Episode i of a batch is the same episode when rolled alone.
    assert evaluate_policy(greedy, episodes=1, seed=6)[0] == returns[1]

    noisy = load_policy(checkpoint, mode="noisy")
    np.testing.assert_array_equal(
        evaluate_policy(noisy, episodes=2, seed=5), evaluate_policy(noisy, episodes=2, seed=5)
    )


@pytest.mark.skipif(not COMMITTED_POLICY.exists(), reason="models/policy.pt not trained yet")
def test_committed_policy_evaluates_as_its_report_says():
    policy = load_policy(COMMITTED_POLICY, state_dim=8, action_size=4)
    assert policy.kind == "noisy_dqn"
    report = json.loads(COMMITTED_POLICY.with_suffix(".json").read_text())
    assert report["evaluation"]["mean"] >= 230  # SPEC §2 bar, over 30 held-out episodes
    returns = evaluate_policy(policy, episodes=2, seed=report["evaluation"]["seeds"][0])
    np.testing.assert_allclose(returns, report["evaluation"]["returns"][:2])
