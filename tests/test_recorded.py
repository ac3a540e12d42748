"""Recorded data (SPEC §18): a Minari dataset as the clean data of a post-hoc pipeline.

Every dataset here is a real Minari dataset, written by minari into a datasets folder under
tmp_path (MINARI_DATASETS_PATH) from random rollouts of a Gymnasium environment. The how-to's
recipe is followed literally in a throw-away git + DVC copy of the project, on tiny params, with
a stand-in of the dataset it names.
"""

from __future__ import annotations

import re
import shlex
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_new import tiny_params
from test_readme import DOCS, blocks, section, shell_commands
from typer.testing import CliRunner

from oodrl.cli import app
from oodrl.config import load_params, read_params_data
from oodrl.errors import ConfigError
from oodrl.suite.new import new_pipeline
from oodrl.suite.pipeline import check_files
from oodrl.testing.pipeline import copy_project, run

SECTION = (DOCS / "how-to" / "your-agent.md", "Recorded data: a Minari dataset")
#: Appended to the how-to's `oodrl new`: streams of 40 steps.
TINY = ["--T", "40"]
#: Two post-hoc faults and one that needs a simulator.
INJECTORS = ["gaussian_state_noise", "observation_delay", "stuck_actuator"]
POSTHOC = INJECTORS[:2]
#: Stages and detector stages that roll a policy out: a recorded pipeline has none of them.
SIMULATED = {
    "train_policy", "impact_reference", "impact", "collect_tiers", "collect_calibration",
    "collect_audit", "collect_twins", "tier_metrics",
}  # fmt: skip
#: Simulated sets a detector file's scoring stages read in a simulated pipeline.
SIMULATED_SETS = ("data/calibration.zarr", "data/audit.zarr", "data/twins.zarr", "data/tiers/")
HOPPER = "mujoco/hopper/medium-v0"  # the how-to's dataset, here a random stand-in


def readme_commands() -> list[str]:
    (script,) = blocks(section(SECTION), "bash")
    return shell_commands(script)


def record(dataset_id: str, env_id: str, steps: int):
    """A Minari dataset of random episodes of `env_id`, `steps` steps in all (the last episode
    cut short, as a recording that stopped)."""
    import gymnasium as gym
    from minari.data_collector.episode_buffer import EpisodeBuffer

    env = gym.make(env_id)
    buffers, total = [], 0
    while total < steps:
        episode = len(buffers)
        env.action_space.seed(episode)
        observations = [env.reset(seed=episode)[0]]
        actions, rewards, terminations, truncations = [], [], [], []
        while total + len(actions) < steps:
            action = env.action_space.sample()
            observation, reward, terminated, truncated, _ = env.step(action)
            observations.append(observation)
            actions.append(action)
            rewards.append(float(reward))
            terminations.append(terminated)
            truncations.append(truncated)
            if terminated or truncated:
                break
        buffers.append(
            EpisodeBuffer(
                id=episode, seed=episode, observations=np.stack(observations),
                actions=np.stack(actions), rewards=rewards, terminations=terminations,
                truncations=truncations, infos={},
            )
        )  # fmt: skip
        total += len(actions)
    return created(dataset_id, buffers, env=env_id)


def record_space(dataset_id: str, observation_space):
    """One 10-step episode of samples of `observation_space`, recorded on no environment."""
    import gymnasium as gym
    from minari.data_collector.episode_buffer import EpisodeBuffer

    observation_space.seed(0)
    samples = [observation_space.sample() for _ in range(11)]
    if isinstance(observation_space, gym.spaces.Dict):
        observations = {key: np.stack([s[key] for s in samples]) for key in observation_space}
    else:
        observations = np.stack(samples)
    buffer = EpisodeBuffer(
        id=0, seed=0, observations=observations, actions=np.zeros((10, 2), np.float32),
        rewards=[0.0] * 10, terminations=[False] * 10, truncations=[False] * 9 + [True], infos={},
    )  # fmt: skip
    actions = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    return created(dataset_id, [buffer], observation_space=observation_space, action_space=actions)


def created(dataset_id: str, buffers: list, **kwargs):
    import minari

    with warnings.catch_warnings():  # minari asks for an author, a description, …
        warnings.simplefilter("ignore", UserWarning)
        return minari.create_dataset_from_buffers(
            dataset_id, buffers, algorithm_name="random", jpeg_encoding=False, **kwargs
        )


@pytest.fixture(scope="module")
def minari_root(tmp_path_factory) -> Path:
    """A Minari datasets folder: the how-to's Hopper stand-in and some that oodrl refuses."""
    import gymnasium as gym

    root = tmp_path_factory.mktemp("minari")
    box = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MINARI_DATASETS_PATH", str(root))
        record(HOPPER, "Hopper-v5", 600)
        record("test/cartpole-short-v0", "CartPole-v1", 30)
        record_space("test/dict-v0", gym.spaces.Dict({"position": box, "goal": box}))
        record_space("test/image-v0", gym.spaces.Box(0, 255, (8, 8, 3), np.uint8))
    return root


@pytest.fixture
def minari_env(minari_root, monkeypatch) -> Path:
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(minari_root))
    return minari_root


@pytest.fixture
def root(tmp_path: Path, repo_root: Path) -> Path:
    """A project of tiny shared params and the package sources (the DVC files' code deps)."""
    params = tiny_params(repo_root)
    params["benchmark"]["injectors"] = INJECTORS
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    (tmp_path / "src").symlink_to(repo_root / "src")
    return tmp_path


def hopper():
    import minari

    return minari.load_dataset(HOPPER)


# -- streams ---------------------------------------------------------------------------------------
def test_streams_are_the_episodes_in_order_run_on_into_the_next_and_cut_at_T(minari_env):
    from oodrl.protocol.recorded import streams

    dataset, T = hopper(), 40
    episodes = list(dataset.iterate_episodes())
    cut = streams(dataset, T, 5)
    a = cut.arrays
    for i in range(5):
        # A stream starts at an episode's start, the one after the previous stream's last.
        first = int(cut.seeds[i])
        previous_last = -1 if i == 0 else int(cut.seeds[i - 1] + a["episode_index"][i - 1, -1])
        assert first == previous_last + 1
        expected = {key: [] for key in ("states", "next_states", "actions", "rewards", "dones")}
        for k in range(int(a["episode_index"][i, -1]) + 1):
            episode = episodes[first + k]
            n = len(episode.rewards)
            expected["states"].append(episode.observations[:-1])
            expected["next_states"].append(episode.observations[1:])
            expected["actions"].append(episode.actions)
            expected["rewards"].append(episode.rewards)
            expected["dones"].append(np.arange(n) == n - 1)  # the recording's episode ended
        for key, parts in expected.items():
            whole = np.concatenate(parts)[:T]
            np.testing.assert_array_equal(a[key][i], whole.astype(a[key].dtype), err_msg=key)
        within = a["episode_index"][i]
        assert within[0] == 0 and set(np.diff(within)) <= {0, 1}
        assert np.array_equal(np.flatnonzero(np.diff(within)), np.flatnonzero(a["dones"][i][:-1]))
    # Hopper's random episodes fall within a few dozen steps: streams do cross episodes.
    assert a["episode_index"][:, -1].max() >= 1


def test_too_few_episodes_is_one_line(minari_env):
    import minari

    from oodrl.protocol.recorded import streams

    with pytest.raises(ConfigError, match=r"gives 0 streams of T=40 steps.*needs 2") as info:
        streams(minari.load_dataset("test/cartpole-short-v0"), 40, 2)
    assert "\n" not in str(info.value)


# -- oodrl new --dataset -------------------------------------------------------------------------
def test_new_makes_a_post_hoc_pipeline_of_the_recording(minari_env, root):
    from oodrl.protocol.recorded import files_sha256
    from oodrl.suite.pipeline import check_pipeline

    made = new_pipeline(root, "hopper_medium", dataset=HOPPER, T=40)
    directory = made.directory
    assert (made.env_id, made.T, made.policy_report) == ("Hopper-v5", 40, None)
    assert made.supported == tuple(POSTHOC)
    assert made.left_out == {"stuck_actuator": made.left_out["stuck_actuator"]}
    assert "needs a simulator and a policy" in made.left_out["stuck_actuator"]
    params = read_params_data(directory / "params.yaml")
    assert params["benchmark"]["injectors"] == POSTHOC
    train = params["policy"]["train"]
    assert (train["algorithm"], train["source"], train["file"]) == (
        "imported", "Minari dataset", HOPPER,
    )  # fmt: skip
    assert train["sha256"] == files_sha256(directory / "dataset")
    faults = yaml.safe_load((directory / "faults.yaml").read_text())
    assert faults["supported"] == POSTHOC and list(faults["left_out"]) == ["stuck_actuator"]
    # The DVC files: the clean sets imported, nothing that rolls a policy out.
    stages = yaml.safe_load((directory / "dvc.yaml").read_text())["stages"]
    assert not SIMULATED & set(stages)
    assert stages["collect_id"]["cmd"].startswith("oodrl import-dataset id --dataset dataset")
    assert "models/policy.pt" not in (directory / "dvc.yaml").read_text()
    for detector_file in directory.glob("detectors/*/dvc.yaml"):
        text = detector_file.read_text()
        assert "oodrl score" in text and not [s for s in SIMULATED_SETS if s in text]
    check_pipeline(directory / "dvc.yaml")  # what `oodrl pipeline write` writes


def test_the_clean_sets_are_the_dataset_and_byte_identical_on_rerun(minari_env, root, tmp_path):
    from oodrl.io.store import read_trajectories
    from oodrl.protocol.recorded import streams
    from oodrl.stages.recorded import import_clean_set

    made = new_pipeline(root, "hopper_medium", dataset=HOPPER, T=40)
    params = load_params(made.directory / "params.yaml")
    n_id, n_ood = params.data.n_id, params.data.n_ood
    expected = streams(hopper(), 40, n_id + n_ood)
    for split, part in (("id", slice(0, n_id)), ("eval", slice(n_id, n_id + n_ood))):
        first, again = tmp_path / f"{split}-1.zarr", tmp_path / f"{split}-2.zarr"
        import_clean_set(params, split, made.directory / "dataset", first)
        import_clean_set(params, split, made.directory / "dataset", again)
        assert first.read_bytes() == again.read_bytes()
        stored = read_trajectories(first)
        np.testing.assert_array_equal(stored.states, expected.arrays["states"][part])
        np.testing.assert_array_equal(stored.seeds, expected.seeds[part])
        assert stored.attrs["dataset"]["id"] == HOPPER and stored.attrs["mode"] == "clean"
        assert str(made.directory) not in str(stored.attrs)  # no host paths in the data
    assert "split" in read_trajectories(tmp_path / "id-1.zarr").attrs


def test_a_changed_dataset_is_refused_by_the_stage(minari_env, root, tmp_path):
    from oodrl.protocol.recorded import clean_set

    made = new_pipeline(root, "hopper_medium", dataset=HOPPER, T=40)
    params = load_params(made.directory / "params.yaml")
    metadata = made.directory / "dataset" / "metadata.json"
    metadata.write_text(metadata.read_text().replace('"random"', '"expert"'))
    with pytest.raises(ConfigError, match="the dataset changed since") as info:
        clean_set(params, "eval", made.directory / "dataset")
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--dataset", "mujoco/hopper/missing-v0"], "is neither a Minari dataset's directory"),
        (["--dataset", "test/dict-v0", "--env", "Pendulum-v1"], "records Dict observations"),
        (["--dataset", "test/image-v0", "--env", "Pendulum-v1"], "records image observations"),
        (["--dataset", HOPPER, "--policy", "agent.zip"], "exactly one of --policy PATH"),
        (["--dataset", HOPPER, "--env", "Walker2d-v5"], "was recorded on Hopper-v5"),
        (["--dataset", "test/cartpole-short-v0"], "gives 0 streams of T=500 steps"),
    ],
)
def test_bad_input_is_one_line_and_leaves_nothing(minari_env, root, arguments, message):
    result = CliRunner().invoke(app, ["new", "x", *arguments, "--root", str(root)])
    assert result.exit_code == 2, result.output
    assert message in result.output and result.output.count("\n") == 1, result.output
    assert not (root / "pipeline").exists() or not any((root / "pipeline").iterdir())


# -- the how-to's recipe, in a git + DVC copy of the project -----------------------------------
@pytest.mark.slow
def test_the_readme_recipe_benchmarks_recorded_data(minari_root, tmp_path, repo_root):
    from oodrl.io.store import read_trajectories
    from oodrl.protocol.recorded import streams

    params = tiny_params(repo_root)
    params["benchmark"]["injectors"] = INJECTORS
    repo = copy_project(repo_root, tmp_path / "repo", params)
    environment = {"MINARI_DATASETS_PATH": str(minari_root)}
    commands = readme_commands()
    assert len(commands) == 3
    outputs = {}
    for command in commands:
        words = shlex.split(command)
        if words[:2] == ["oodrl", "new"]:
            command = shlex.join([*words, *TINY])
        done = run(repo, "bash", "-c", command, env=environment)
        outputs[words[1] if words[0] == "oodrl" else "repro"] = done.stdout + done.stderr
    name = shlex.split(commands[0])[2]
    pipeline = repo / "pipeline" / name
    ran = {line.split("'")[1] for line in outputs["repro"].splitlines()
           if line.startswith("Running stage '")}  # fmt: skip
    assert {"collect_id", "collect_eval", "metrics", "render"} <= ran
    assert not {stage.split("@")[0].split(":")[-1] for stage in ran} & SIMULATED
    assert not list((pipeline / "scores").glob("*/tiers"))
    # Metrics for the post-hoc faults; the online one never collected or scored.
    results = yaml.safe_load((pipeline / "reports" / "results.yaml").read_text())
    anomalies = {r["injector"] for r in results["records"] if r["kind"] == "anomaly"}
    assert anomalies == set(POSTHOC), anomalies
    assert sorted(p.stem for p in (pipeline / "data" / "ood").glob("*.zarr")) == sorted(POSTHOC)
    assert "gaussian_state_noise" in outputs["show"] and "stuck_actuator" not in outputs["show"]
    # The clean evaluation streams are the dataset's observations.
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MINARI_DATASETS_PATH", str(minari_root))
        n_id, n_ood = params["data"]["n_id"], params["data"]["n_ood"]
        expected = streams(hopper(), 40, n_id + n_ood).arrays["states"][n_id:]
    np.testing.assert_array_equal(
        read_trajectories(pipeline / "data" / "eval.zarr").states, expected
    )
    # Every generated file is current; the root pipeline and the suite were left as they were.
    # (The generated files only: the copy's tiny params leave its locks stale by design.)
    check_files(repo)
    untouched = run(repo, "git", "status", "--porcelain", "--", "dvc.yaml", "pipeline/suite")
    assert untouched.stdout == ""
    assert re.search(r"Hopper-v5, T=40; recorded data " + re.escape(HOPPER), outputs["new"])
