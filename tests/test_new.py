"""`oodrl new` (SPEC §18): your agent, your environment, a pipeline in one command.

The "Benchmark your own agent" block of docs/how-to/your-agent.md is followed literally in a
throw-away git + DVC copy of the project, on tiny params: a PPO agent trained here on
MountainCarContinuous-v0 (not in the suite) under VecNormalize, converted by `oodrl new`, then `dvc
repro` and `oodrl show`.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_readme import DOCS, blocks, section, shell_commands
from typer.testing import CliRunner

from oodrl.cli import app
from oodrl.config import read_params_data
from oodrl.suite.new import new_pipeline
from oodrl.suite.pipeline import check_files
from oodrl.testing.pipeline import TINY_TIERS, copy_project, run

SECTION = (DOCS / "how-to" / "your-agent.md", "Benchmark your own agent")
#: Appended to the how-to's `oodrl new`: streams of 40 steps, a 2-episode report.
TINY = ["--T", "40", "--episodes", "2"]
#: The tiny protocol: a fault every environment has, one only MuJoCo ones have.
INJECTORS = ["stuck_actuator", "dynamics_scaling"]
DYNAMICS = ("action_conditioned_dynamics", "dynamics_scaling", "gradual_drift")


def readme_commands() -> list[str]:
    (script,) = blocks(section(SECTION), "bash")
    return shell_commands(script)


def tiny_params(repo_root: Path) -> dict:
    params = read_params_data(repo_root / "ci" / "params.yaml")
    params["benchmark"] = {"detectors": ["mahalanobis_distance"], "injectors": INJECTORS}
    params["data"].update(n_id=4, n_ood=3)
    params["anomaly"]["sweep"] = [0.5]
    params["metrics"]["n_boot"] = 20
    params["tiers"].update({**TINY_TIERS, "grid": [1.0]})
    params["executor"]["workers"] = 1
    return params


def train_agent(path: Path, env_id: str) -> None:
    """A small PPO agent under VecNormalize: `path` and vecnormalize.pkl beside it."""
    import gymnasium as gym
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    torch.set_num_threads(1)
    venv = VecNormalize(DummyVecEnv([lambda: gym.make(env_id)]), norm_reward=False)
    model = PPO("MlpPolicy", venv, n_steps=512, batch_size=128, n_epochs=2, seed=0, device="cpu")
    model.learn(2048)
    model.save(path)
    venv.save(path.with_name("vecnormalize.pkl"))


#: The environment of the how-to's agent and of the RL Zoo folder's.
AGENT_ENV = "MountainCarContinuous-v0"


@pytest.fixture(scope="module")
def agent(tmp_path_factory) -> Path:
    """One PPO agent on AGENT_ENV, trained once for the module (the how-to's agent and the RL
    Zoo run's): agent.zip and vecnormalize.pkl beside it, which tests copy, never change."""
    path = tmp_path_factory.mktemp("agent") / "agent.zip"
    train_agent(path, AGENT_ENV)
    return path


def place_agent(agent: Path, model: Path, normalization: Path) -> None:
    shutil.copy(agent, model)
    shutil.copy(agent.with_name("vecnormalize.pkl"), normalization)


@pytest.fixture(scope="module")
def followed(tmp_path_factory, repo_root, agent) -> tuple[Path, dict[str, str]]:
    """The how-to's three commands in a fresh project; the output of each."""
    repo = copy_project(repo_root, tmp_path_factory.mktemp("new") / "repo", tiny_params(repo_root))
    commands = readme_commands()
    new = shlex.split(commands[0])
    policy = repo / new[new.index("--policy") + 1]
    assert new[new.index("--env") + 1] == AGENT_ENV
    place_agent(agent, policy, policy.with_name("vecnormalize.pkl"))
    outputs = {}
    for command in commands:
        words = shlex.split(command)
        if words[:2] == ["oodrl", "new"]:
            command = shlex.join([*words, *TINY])
        done = run(repo, "bash", "-c", command)
        outputs[words[1] if words[0] == "oodrl" else "repro"] = done.stdout + done.stderr
    return repo, outputs


@pytest.mark.slow
def test_the_readme_block_benchmarks_an_agent_outside_the_suite(followed):
    repo, outputs = followed
    commands = readme_commands()
    assert len(commands) == 3
    name = shlex.split(commands[0])[2]
    pipeline = repo / "pipeline" / name
    assert "Running stage 'metrics'" in outputs["repro"]
    results = yaml.safe_load((pipeline / "reports" / "results.yaml").read_text())
    assert results  # the protocol ran on the environment: detectors scored, metrics computed
    assert "matched AUROC" in outputs["show"] and "stuck_actuator" in outputs["show"]
    # The root pipeline and the suite were left as they were; every generated file is current.
    untouched = run(repo, "git", "status", "--porcelain", "--", "dvc.yaml", "pipeline/suite")
    assert untouched.stdout == ""
    # Only the generated files: the copy's tiny params leave its locks stale by design.
    check_files(repo)


@pytest.mark.slow
def test_the_new_pipeline_holds_the_converted_agent_and_its_supported_faults(followed):
    repo, outputs = followed
    name = shlex.split(readme_commands()[0])[2]
    pipeline = repo / "pipeline" / name
    params = read_params_data(pipeline / "params.yaml")
    assert (params["env"]["id"], params["env"]["T"]) == ("MountainCarContinuous-v0", 40)
    assert params["policy"]["train"]["algorithm"] == "imported"
    assert params["policy"]["train"]["source"] == "Stable-Baselines3 PPO .zip"
    # MountainCarContinuous has no state vector: the dynamics fault is left out, with why.
    assert params["benchmark"]["injectors"] == ["stuck_actuator"]
    faults = yaml.safe_load((pipeline / "faults.yaml").read_text())
    assert faults["supported"] == ["stuck_actuator"]
    assert "no state vector" in faults["left_out"]["dynamics_scaling"]
    assert "left out: dynamics_scaling" in outputs["new"]
    report = json.loads((pipeline / "models" / "policy.json").read_text())
    assert report["evaluation"]["episodes"] == 2
    checkpoint = pipeline / "models" / "policy.pt"
    architecture = __import__("torch").load(checkpoint, weights_only=True)["architecture"]
    assert architecture["kind"] == "clipped_actor" and "observation_normalization" in architecture
    stores = sorted(p.name for p in (pipeline / "data" / "ood").glob("*.zarr"))
    assert stores == ["stuck_actuator.zarr"]


@pytest.mark.slow
def test_a_second_new_with_the_same_name_is_refused(followed):
    repo, _ = followed
    command = shlex.split(readme_commands()[0])
    done = run(repo, *command, check=False)
    assert done.returncode == 2
    assert re.fullmatch(r"error: NAME: .* exists already; .*\n", done.stderr)


# -- bad input: one line, exit 2, nothing left behind ------------------------------------------
@pytest.fixture
def root(tmp_path: Path, repo_root: Path) -> Path:
    """A project of the shared params and the package sources (the DVC files' code deps)."""
    (tmp_path / "params.yaml").write_text((repo_root / "params.yaml").read_text())
    (tmp_path / "src").symlink_to(repo_root / "src")
    return tmp_path


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["x", "--env", "MountainCarContinuos-v0", "--train", "ppo"], "--env: Unknown environment"),
        (["x", "--env", "CarRacing-v3", "--train", "ppo"], "need a feature extractor"),
        (["x", "--env", "MountainCar-v0"], "exactly one of --policy PATH, --train"),
        (["X-1", "--env", "MountainCar-v0", "--train", "ppo"], "not a pipeline name"),
        (["x", "--env", "MountainCar-v0", "--train", "sac"], "SAC needs continuous actions"),
        (["x", "--env", "MountainCar-v0", "--train", "a3c"], "--train: 'a3c'; allowed"),
        (["x", "--env", "MountainCar-v0", "--policy", "missing.zip"], "no such file"),
    ],
)
def test_bad_input_is_one_line_and_leaves_nothing(root: Path, arguments, message):
    result = CliRunner().invoke(app, ["new", *arguments, "--root", str(root), "--steps", "1"])
    assert result.exit_code in (1, 2), result.output
    assert message in result.output and result.output.count("\n") == 1, result.output
    assert not (root / "pipeline").exists() or not any((root / "pipeline").iterdir())


def test_version_is_the_installed_one():
    from importlib.metadata import version

    result = CliRunner().invoke(app, ["--version"])
    assert result.exit_code == 0 and result.output == f"oodrl {version('oodrl')}\n"


# -- other policies ----------------------------------------------------------------------------
def test_a_module_function_policy_is_a_pointer_marked_not_certified(root, tmp_path, monkeypatch):
    (tmp_path / "my_controller.py").write_text(
        "import numpy as np\n\n"
        "def act(observations):\n"
        "    return np.where(observations[:, 1:2] > 0, 1.0, -1.0)  # push along the velocity\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    made = new_pipeline(
        root, "energy", "MountainCarContinuous-v0", policy="my_controller:act", T=30, episodes=2
    )
    pointer = json.loads((made.directory / "models" / "policy.pt").read_text())
    assert pointer["callable"] == "my_controller:act"
    assert pointer["certified_machine_independent"] is False
    assert made.policy_report["evaluation"]["mean"] > 50  # the textbook energy controller wins
    assert set(made.left_out) == set(DYNAMICS)
    from oodrl.policies.load import load_policy

    actions = load_policy(made.directory / "models" / "policy.pt").act(np.zeros((3, 2)), None)
    assert actions.shape == (3, 1) and actions.dtype == np.float32


@pytest.mark.slow
def test_train_on_a_mujoco_environment_supports_every_fault(root):
    made = new_pipeline(root, "pendulum_agent", "InvertedPendulum-v5", train="ppo", steps=256,
                        episodes=1)  # fmt: skip
    assert made.T == 1000 and made.left_out == {}
    params = read_params_data(made.directory / "params.yaml")
    assert "benchmark" not in (yaml.safe_load((made.directory / "params.yaml").read_text()))
    predicate = params["anomaly"]["injectors"]["action_conditioned_dynamics"]
    assert predicate["target_dim"] == 0 and -3 <= predicate["target_threshold"] < 3
    assert (made.directory / "models" / "sb3_ppo.zip").is_file()
    assert (made.directory / "dvc.yaml").is_file()
    assert (made.directory / ".dvc" / "config").is_file()


@pytest.mark.slow
def test_an_rl_zoo_folder_becomes_a_pipeline_of_its_own_environment(root, tmp_path, agent):
    """logs/ppo/<env>_1/ as rl-zoo3 writes it; the folder names the environment it ran on."""
    from collections import OrderedDict

    env_id = AGENT_ENV
    run_dir = tmp_path / "logs" / "ppo" / f"{env_id}_1"
    (run_dir / env_id).mkdir(parents=True)
    place_agent(agent, run_dir / f"{env_id}.zip", run_dir / env_id / "vecnormalize.pkl")
    (run_dir / env_id / "config.yml").write_text(yaml.dump(OrderedDict(normalize=True)))
    wrong = CliRunner().invoke(
        app, ["new", "x", "--env", "Pendulum-v1", "--policy", str(run_dir), "--root", str(root)]
    )
    assert wrong.exit_code == 2 and f"an RL Zoo run on {env_id}" in wrong.output
    made = new_pipeline(root, "zoo", env_id, policy=str(run_dir), T=30, episodes=1)
    train = read_params_data(made.directory / "params.yaml")["policy"]["train"]
    assert (train["source"], train["file"]) == ("RL Zoo folder", f"{env_id}.zip")
    assert (
        "observation_normalization"
        in json.loads((made.directory / "models" / "policy.json").read_text())["architecture"]
    )
