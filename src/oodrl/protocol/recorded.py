"""Recorded data: a Minari dataset on disk as the clean data of a post-hoc pipeline (SPEC §18).

`oodrl new NAME --dataset PATH_OR_ID` copies the dataset's files into `pipeline/NAME/dataset/`;
the pipeline's collect_id and collect_eval stages (`oodrl import-dataset`) cut its episodes
into the protocol's streams of T steps:

- Episodes are read in the dataset's order. A stream starts at the start of an episode (as a
  simulated stream starts at a reset) and, where the episode ends before T steps, runs on into
  the next one, as the collector resets into the next episode: `dones` marks the boundary
  (the recording's episode ended there, terminated, truncated or cut), `next_states` is the
  episode's last observation, `episode_index` counts the stream's episodes. An episode longer
  than what is left of the stream is cut there; its remaining steps are not used.
- The ID set is the first `data.n_id` streams (fit and calibration split as for simulated
  data, `oodrl.protocol.streams.fit_calibration_split`), the evaluation set the `data.n_ood` streams
  after them. A stream's `seeds` entry is the position of its first episode in the dataset,
  so step t of stream i is from the dataset's episode `seeds[i] + episode_index[i, t]`.

Nothing host- or time-dependent enters the stores: the sets' attributes name the dataset by
its id and the sha256 of its files. `minari` is imported only by the functions that read a
dataset (the `minari` extra).
"""

from __future__ import annotations

import hashlib
import re
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from oodrl.errors import ConfigError

if TYPE_CHECKING:
    import gymnasium as gym

    from oodrl.config import Params
    from oodrl.core.adapter import EnvironmentAdapter
    from oodrl.core.trajectory import TrajectorySet

#: `policy.train.source` of a recorded pipeline: the generator renders its post-hoc stages
#: (recorded_pipeline.yaml) for it, and collect_id/collect_eval check the dataset's sha256.
SOURCE = "Minari dataset"
#: The dataset's copy in the pipeline's directory, the clean sets' one input.
DATASET_DIR = "dataset"
#: Why a fault that acts during a rollout is left out of a recorded pipeline.
NO_SIMULATOR = "needs a simulator and a policy: this pipeline's clean data are recorded"
#: Minari's file describing a dataset (spaces, environment, counts), in its data directory.
METADATA = "metadata.json"


def _minari():
    try:
        import minari
    except ImportError:
        raise ConfigError(
            "--dataset: reading Minari datasets needs the minari extra: pip install -e '.[minari]'."
        ) from None
    return minari


#: What a Minari dataset id is made of ([namespace/]name[-vN], minari's DATASET_ID_RE): a
#: --dataset with anything else (., ~, a leading /, a backslash) names a directory.
_ID_CHARACTERS = re.compile(r"[-\w][-\w/]*")


def _names_a_directory(dataset: str) -> bool:
    """Whether --dataset is a path rather than a Minari id. Ids have `/` too (mujoco/hopper/
    expert-v0), so a path is one with a character no id has (./data, ~/d, /abs, d.h5), or one
    whose first part is a directory here (data/my_dataset with a data/ beside it)."""
    if not _ID_CHARACTERS.fullmatch(dataset):
        return True
    first, separator, _ = dataset.partition("/")
    return bool(separator) and Path(first).is_dir()


def locate(dataset: str) -> Path:
    """The data directory (holding metadata.json) of a dataset given as a path or a Minari id
    of the local datasets (MINARI_DATASETS_PATH, else ~/.minari/datasets)."""
    path = Path(dataset).expanduser()
    if path.exists() or _names_a_directory(dataset):
        for candidate in (path, path / "data"):
            if (candidate / METADATA).is_file():
                return candidate
        if not path.exists():
            raise ConfigError(f"--dataset: no such dataset directory: {dataset}")
        raise ConfigError(
            f"--dataset: {dataset} is not a Minari dataset's directory (no {METADATA} in it "
            "or in its data/)."
        )
    path = _minari().storage.get_dataset_path(dataset)
    for candidate in (path, path / "data"):
        if (candidate / METADATA).is_file():
            return candidate
    raise ConfigError(
        f"--dataset: {dataset} is neither a Minari dataset's directory nor the id of a local "
        f"Minari dataset (looked in {path}); `minari download {dataset}` fetches a remote one."
    )


def load(data_dir: Path):
    """The MinariDataset in `data_dir`, its spaces checked (a one-line ConfigError)."""
    minari = _minari()
    try:
        dataset = minari.MinariDataset(data_dir)
    except Exception as error:  # h5py, pyarrow and json raise many kinds on damaged files
        raise ConfigError(
            f"--dataset: {data_dir} is not a readable Minari dataset ({error})."
        ) from None
    check_spaces(dataset.spec.dataset_id, dataset.observation_space, dataset.action_space)
    return dataset


def check_spaces(name: str, observations: gym.Space, actions: gym.Space) -> None:
    """A flat Box observation and Discrete (from 0) or 1-dim Box actions, as oodrl stores them."""
    from gymnasium import spaces

    if not (isinstance(observations, spaces.Box) and len(observations.shape) == 1):
        shape = getattr(observations, "shape", None) or ()
        what = "image" if len(shape) == 3 else type(observations).__name__
        raise ConfigError(
            f"--dataset: {name} records {what} observations ({observations}); oodrl needs a "
            "flat Box observation (one vector per step)."
        )
    discrete = isinstance(actions, spaces.Discrete) and actions.start == 0
    if not (discrete or (isinstance(actions, spaces.Box) and len(actions.shape) == 1)):
        raise ConfigError(
            f"--dataset: {name} records actions of {actions}; oodrl supports Discrete actions "
            "starting at 0 and 1-dim Box actions."
        )


def check_environment(dataset, adapter: EnvironmentAdapter) -> None:
    """The dataset's observations and actions are the environment's (the params are checked
    against the environment's spaces; no stage steps it)."""
    name, env_id = dataset.spec.dataset_id, adapter.env_id
    size = dataset.observation_space.shape[0]
    if size != adapter.state_dim:
        raise ConfigError(
            f"--dataset: {name} records {size}-dim observations; {env_id} gives "
            f"{adapter.state_dim}-dim ones."
        )
    actions = dataset.action_space
    kind = "discrete" if actions.shape == () else "continuous"
    count = int(actions.n) if kind == "discrete" else actions.shape[0]
    if (kind, count) != (adapter.action_kind, adapter.action_size):
        raise ConfigError(
            f"--dataset: {name} records {count} {kind} actions; {env_id} has "
            f"{adapter.describe_actions()}."
        )


def recorded_env_id(dataset) -> str | None:
    """The Gymnasium id the dataset was recorded on, or None when it records none."""
    spec = dataset.spec.env_spec
    return None if spec is None else spec.id


def files_sha256(data_dir: Path) -> str:
    """sha256 over the dataset's files (relative path and content, sorted by path)."""
    digest = hashlib.sha256()
    for path in sorted(p for p in Path(data_dir).rglob("*") if p.is_file()):
        content = hashlib.sha256(path.read_bytes()).hexdigest()
        digest.update(f"{content}  {path.relative_to(data_dir).as_posix()}\n".encode())
    return digest.hexdigest()


def copy(data_dir: Path, destination: Path) -> None:
    """The dataset's files, as Minari keeps them, into the pipeline's `destination`."""
    shutil.copytree(data_dir, destination)


# -- streams ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Streams:
    """The first streams of T steps a dataset gives, as a TrajectorySet's arrays."""

    arrays: dict[str, np.ndarray]
    seeds: np.ndarray

    def part(self, start: int, stop: int) -> dict[str, Any]:
        arrays = {name: value[start:stop] for name, value in self.arrays.items()}
        executed = arrays["actions"].copy()  # no faults: the commanded actions ran
        return {**arrays, "executed_actions": executed, "seeds": self.seeds[start:stop]}


def streams(dataset, T: int, count: int) -> Streams:  # noqa: N803 - the protocol's name
    """The dataset's first `count` streams of T steps (see the module docstring); a one-line
    ConfigError when its episodes give fewer."""
    discrete = dataset.action_space.shape == ()
    dim = dataset.observation_space.shape[0]
    action_shape = () if discrete else dataset.action_space.shape
    arrays = {
        "states": np.zeros((count, T, dim), np.float32),
        "next_states": np.zeros((count, T, dim), np.float32),
        "actions": np.zeros((count, T, *action_shape), np.int64 if discrete else np.float32),
        "rewards": np.zeros((count, T), np.float32),
        "dones": np.zeros((count, T), bool),
        "episode_index": np.zeros((count, T), np.int32),
    }
    seeds = np.zeros(count, np.int64)
    episodes = _episodes(dataset)
    for i in range(count):
        t = within = 0
        while t < T:
            try:
                position, episode = next(episodes)
            except StopIteration:
                raise ConfigError(
                    f"{dataset.spec.dataset_id} gives {i} streams of T={T} steps (each starts "
                    f"at an episode's start and runs on into the next episodes); the protocol "
                    f"needs {count}: lower env.T (--T), data.n_id or data.n_ood."
                ) from None
            if within == 0:
                seeds[i] = position
            length = len(episode.rewards)
            k = min(length, T - t)
            observations = np.asarray(episode.observations)
            arrays["states"][i, t : t + k] = observations[:k]
            arrays["next_states"][i, t : t + k] = observations[1 : k + 1]
            arrays["actions"][i, t : t + k] = np.asarray(episode.actions)[:k]
            arrays["rewards"][i, t : t + k] = np.asarray(episode.rewards)[:k]
            arrays["dones"][i, t + k - 1] = k == length
            arrays["episode_index"][i, t : t + k] = within
            t, within = t + k, within + 1
    return Streams(arrays, seeds)


def _episodes(dataset) -> Iterator[tuple[int, Any]]:
    """(position in the dataset, episode) of every episode with at least one step, in order."""
    for position, episode in enumerate(dataset.iterate_episodes()):
        if len(episode.rewards):
            yield position, episode


# -- the clean sets -----------------------------------------------------------------------------
SPLITS = ("id", "eval")


def clean_set(params: Params, split: str, data_dir: Path) -> TrajectorySet:
    """The clean ID set (`split` 'id', with its fit/calibration split) or evaluation set
    ('eval') of a recorded pipeline, from the dataset's copy in `data_dir`."""
    from oodrl.core.trajectory import TrajectorySet
    from oodrl.protocol.streams import fit_calibration_split

    sha256 = files_sha256(data_dir)
    recorded = params.policy.train.get("sha256")
    if params.policy.train.get("source") != SOURCE or recorded != sha256:
        raise ConfigError(
            f"{data_dir}: its files have sha256 {sha256}; params' policy.train (source "
            f"{SOURCE!r}) records {recorded}: the dataset changed since `oodrl new --dataset` "
            f"copied it. To benchmark this one, set policy.train.sha256: {sha256}."
        )
    dataset = load(data_dir)
    n_id, n_ood = params.data.n_id, params.data.n_ood
    start, stop = (0, n_id) if split == "id" else (n_id, n_id + n_ood)
    cut = streams(dataset, params.env.T, stop)
    attrs: dict[str, Any] = {
        "env_id": params.env.id,
        "T": params.env.T,
        "onset": params.env.resolved_onset,
        "seed": params.seed,
        "mode": "clean",
        "spec": None,
        "dataset": {"id": dataset.spec.dataset_id, "sha256": sha256},
    }
    if split == "id":
        fit, calibration = fit_calibration_split(params)
        attrs["split"] = {"calibration": calibration, "fit": fit}
    return TrajectorySet(**cut.part(start, stop), attrs=attrs)
