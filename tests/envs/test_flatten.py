"""`oodrl new --flatten` (SPEC §18): an environment with a Dict or Tuple observation, wrapped in
gymnasium.wrappers.FlattenObservation by name (`FlattenObservation(<id>)` in params), so every
stage makes the same wrapped environment.

The Dict environment is a real Gymnasium environment made and registered here: a point mass
observed as {position, velocity}.
"""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import yaml
from gymnasium import spaces
from typer.testing import CliRunner

from oodrl.cli import app
from oodrl.config import load_params, read_params_data
from oodrl.envs import ENVIRONMENTS, GENERIC_ADAPTER
from oodrl.envs.collect import collect
from oodrl.errors import ContractError
from oodrl.suite.new import new_pipeline

DICT_ENV = "oodrl_test/DictPoint-v0"
FLAT = f"FlattenObservation({DICT_ENV})"


class DictPoint(gym.Env):
    """A point on a plane pushed by a 2-dim force, observed as a Dict."""

    def __init__(self) -> None:
        box = spaces.Box(-10.0, 10.0, (2,), np.float32)
        self.observation_space = spaces.Dict({"position": box, "velocity": box})
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)

    def _observation(self) -> dict[str, np.ndarray]:
        return {"position": self.position.copy(), "velocity": self.velocity.copy()}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.position = self.np_random.uniform(-1, 1, 2).astype(np.float32)
        self.velocity = np.zeros(2, np.float32)
        return self._observation(), {}

    def step(self, action):
        self.velocity = np.clip(self.velocity + 0.1 * np.asarray(action, np.float32), -10, 10)
        self.position = np.clip(self.position + 0.1 * self.velocity, -10, 10)
        return self._observation(), -float(np.linalg.norm(self.position)), False, False, {}


@pytest.fixture(scope="module", autouse=True)
def registered():
    gym.register(DICT_ENV, entry_point=DictPoint, max_episode_steps=50)
    yield
    del gym.registry[DICT_ENV]


@pytest.fixture
def root(tmp_path: Path, repo_root: Path, monkeypatch) -> Path:
    """The shared params, the package sources, and a controller importable as a policy."""
    (tmp_path / "params.yaml").write_text((repo_root / "params.yaml").read_text())
    (tmp_path / "src").symlink_to(repo_root / "src")
    (tmp_path / "point_controller.py").write_text(
        "import numpy as np\n\n"
        "def act(observations):  # flat: position (2), then velocity (2)\n"
        "    return np.clip(-observations[:, :2] - observations[:, 2:], -1, 1)\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


def test_a_dict_observation_without_the_flag_is_one_line_naming_it(root):
    with pytest.raises(ContractError, match="--flatten") as info:
        ENVIRONMENTS.get(DICT_ENV)().make()
    assert "\n" not in str(info.value) and "Dict" in str(info.value)
    arguments = ["new", "x", "--env", DICT_ENV, "--policy", "point_controller:act"]
    result = CliRunner().invoke(app, [*arguments, "--root", str(root)])
    assert result.exit_code == 2 and result.output.count("\n") == 1, result.output
    assert "`oodrl new --flatten` wraps it" in result.output
    assert not (root / "pipeline").exists() or not any((root / "pipeline").iterdir())


def test_the_flattened_name_is_a_generic_adapter_of_flat_observations():
    adapter = ENVIRONMENTS.get(FLAT)()
    assert ENVIRONMENTS.path(FLAT) == GENERIC_ADAPTER
    assert (adapter.state_dim, adapter.action_kind, adapter.action_size) == (4, "continuous", 2)
    # A built-in with a Tuple observation too: Blackjack's three Discretes, one-hot.
    assert ENVIRONMENTS.get("FlattenObservation(Blackjack-v1)")().state_dim == 32 + 11 + 2


def test_new_with_the_flag_names_the_wrapped_environment_and_rolls_out_flat(root):
    made = new_pipeline(root, "dict_point", DICT_ENV, policy="point_controller:act", flatten=True,
                        T=30, episodes=2)  # fmt: skip
    params = load_params(made.directory / "params.yaml")
    assert made.env_id == params.env.id == FLAT and params.env.T == 30
    assert read_params_data(made.directory / "params.yaml")["policy"]["train"]["env_id"] == FLAT
    assert json.loads((made.directory / "models" / "policy.json").read_text())
    faults = yaml.safe_load((made.directory / "faults.yaml").read_text())
    assert "dynamics_scaling" in faults["left_out"]  # no state vector outside MuJoCo
    # What every stage makes from params: flat observations, the Dict env's flattened.
    from oodrl.policies.load import load_policy

    adapter = ENVIRONMENTS.get(params.env.id)()
    policy = load_policy(made.directory / "models" / "policy.pt")
    clean = collect(adapter, policy, [7], 20)
    assert clean.states.shape == (1, 20, 4)
    env = gym.make(DICT_ENV)
    observation = env.reset(seed=7)[0]
    for t in range(20):
        flat = spaces.flatten(env.observation_space, observation)
        np.testing.assert_array_equal(clean.states[0, t], flat.astype(np.float32))
        observation = env.step(clean.actions[0, t])[0]


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--env", "Pendulum-v1", "--policy", "point_controller:act"], "observes a flat Box"),
        (["--dataset", "some/dataset-v0"], "--flatten: it wraps an agent's environment"),
        (["--env", "DictPont-v0", "--policy", "point_controller:act"], "Unknown environment"),
    ],
)
def test_the_flag_where_it_has_nothing_to_do_is_refused(root, arguments, message):
    result = CliRunner().invoke(app, ["new", "x", *arguments, "--flatten", "--root", str(root)])
    assert result.exit_code == 2 and message in result.output, result.output
    assert result.output.count("\n") == 1, result.output
