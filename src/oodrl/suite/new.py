"""`oodrl new NAME --env ENV_ID --policy PATH`: a pipeline for your agent in your environment.

Makes `pipeline/NAME/` (SPEC §18): the agent as an oodrl policy (`models/policy.pt`, converted
from a Stable-Baselines3 .zip, an RL Zoo folder or an oodrl checkpoint, or a `module:function`
pointer; `--train` trains one with SB3 instead), its params.yaml (T from the environment's
episode length; the shared protocol's detectors; the faults the environment supports, with the
action predicate of `action_conditioned_dynamics` read from the policy's own clean actions),
`faults.yaml` (each fault left out, and why), and its DVC files, written by the generator
every pipeline comes from (`oodrl.suite.pipeline`). `cd pipeline/NAME && dvc repro` then runs
the protocol.

`--flatten` wraps an environment with a Dict, Tuple or other non-flat observation in
gymnasium.wrappers.FlattenObservation: params name it `FlattenObservation(<id>)`, so every stage
makes the wrapped environment (`oodrl.envs`).

`--dataset PATH_OR_ID` makes a pipeline of recorded data instead (`oodrl.protocol.recorded`): a
Minari dataset's episodes are its clean streams, so it has no policy and runs the post-hoc
faults only.

Everything (params, faults, models, DVC files) is made in a staging folder beside it,
`pipeline/.NAME.new-<pid>`, and moved into place by one rename at the very end, so a refused or
interrupted command (SIGINT, SIGTERM, SIGHUP: SPEC §22) leaves nothing behind: `pipeline/NAME`
is complete or absent. A staging folder whose process died without cleaning up (SIGKILL) is
removed by the next `oodrl new`.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from oodrl.errors import ConfigError, ContractError, OodrlError, PolicyError
from oodrl.suite.scratch import STAGING_PATTERN, remove_dead, remove_dead_runs

if TYPE_CHECKING:
    from oodrl.config import Params
    from oodrl.core.adapter import EnvironmentAdapter

NAME_PATTERN = re.compile(r"[a-z][a-z0-9_]*")
#: The signals that end `oodrl new` with its staging folder removed. SIGINT raises
#: KeyboardInterrupt already; these two raise SystemExit meanwhile (`_signals_end_staging`).
ENDING_SIGNALS = (signal.SIGTERM, signal.SIGHUP)
#: The first seed of the held-out episodes of the policy's report, and the seed of the clean
#: stream its action predicate is read from (the ID and evaluation sets use seeds from 0).
EVALUATION_SEED = 1_000_000
PREDICATE_FAULT = "action_conditioned_dynamics"
#: SPEC §4: `action_conditioned_dynamics` should hold on about a third to a half of clean steps;
#: the threshold is the clean actions' quantile that leaves this share above it.
PREDICATE_SHARE = 0.4
#: `gradual_drift` reaches its full factor this far into the post-onset steps (root: 200/334).
RAMP_SHARE = 0.6


@dataclass(frozen=True)
class NewPipeline:
    directory: Path
    env_id: str
    T: int
    supported: tuple[str, ...]
    left_out: dict[str, str]
    policy_report: dict[str, Any] | None
    #: A pipeline of recorded data: what its dataset holds (None for an agent's pipeline).
    recording: str | None = None


def new_pipeline(
    root: Path,
    name: str,
    env_id: str | None = None,
    *,
    policy: str | None = None,
    train: str | None = None,
    dataset: str | None = None,
    flatten: bool = False,
    steps: int = 50_000,
    T: int | None = None,  # noqa: N803 - the protocol's name
    episodes: int = 10,
    seed: int = 0,
) -> NewPipeline:
    """Make `root/pipeline/NAME/` (see the module docstring); a one-line error otherwise. One
    `oodrl new` (or suite run) at a time per checkout (`oodrl.suite.checkout_lock`); the
    temporary folders of dead runs go first."""
    from oodrl.suite.checkout_lock import checkout_lock

    with checkout_lock(root, "new"):
        remove_dead_runs(root)
        return _new_pipeline(
            root, name, env_id, policy=policy, train=train, dataset=dataset, flatten=flatten,
            steps=steps, T=T, episodes=episodes, seed=seed,
        )  # fmt: skip


def _new_pipeline(
    root: Path,
    name: str,
    env_id: str | None,
    *,
    policy: str | None,
    train: str | None,
    dataset: str | None,
    flatten: bool,
    steps: int,
    T: int | None,  # noqa: N803 - the protocol's name
    episodes: int,
    seed: int,
) -> NewPipeline:
    from oodrl.suite.pipeline import ENVIRONMENTS_DIR

    directory = root / ENVIRONMENTS_DIR / name
    _check_name(name, directory)
    if sum(source is not None for source in (policy, train, dataset)) != 1:
        raise ConfigError(
            "oodrl new: give exactly one of --policy PATH, --train sac|ppo|dqn and "
            "--dataset PATH_OR_ID."
        )
    if env_id is not None:
        _check_env_id(env_id)
    if dataset is not None:
        if flatten:
            raise ConfigError("--flatten: it wraps an agent's environment, not a dataset.")
        return _recorded_pipeline(root, directory, dataset, env_id, T)
    if env_id is None:
        raise ConfigError("--env: name the agent's environment (a Gymnasium id).")
    _refuse_images(env_id)
    if flatten:
        env_id = _flattened(env_id)
    adapter = _adapter(env_id)
    T = T or episode_length(env_id)  # noqa: N806
    shared = _shared_params(root)
    with _staged(directory, root) as staging:
        models = staging / "models"
        models.mkdir()
        report = _make_policy(
            policy, train, env_id, models, steps=steps, episodes=episodes, seed=seed
        )
        _check_beats_random(report, adapter, None if train is None else steps)
        from oodrl.envs.collect import collect
        from oodrl.policies.load import load_policy

        support = fault_support(adapter, list(shared.benchmark.injectors))
        clean = collect(adapter, load_policy(models / "policy.pt"), [EVALUATION_SEED], T)
        blocks, predicate_reason = injector_blocks(adapter, clean.actions[0], T)
        if predicate_reason and PREDICATE_FAULT in support and support[PREDICATE_FAULT] is None:
            support[PREDICATE_FAULT] = predicate_reason
        note = "imported by `oodrl new`: kept, never trained here"
        params = params_text(name, env_id, T, report["train_config"], support, blocks, note)
        _write_params(staging, params, faults_text(env_id, support))
    return NewPipeline(directory, env_id, T, *_split(support), report)


def _recorded_pipeline(
    root: Path,
    directory: Path,
    dataset: str,
    env_id: str | None,
    T: int | None,  # noqa: N803
) -> NewPipeline:
    """A pipeline of recorded data (`oodrl.protocol.recorded`): the dataset copied in, its params
    naming it (`policy.train`: source, id, sha256), the post-hoc faults only."""
    from oodrl.protocol import recorded

    data_dir = recorded.locate(dataset)
    data = recorded.load(data_dir)
    dataset_id = data.spec.dataset_id
    env_id = _recorded_env(dataset_id, recorded.recorded_env_id(data), env_id)
    adapter = _adapter(env_id)
    recorded.check_environment(data, adapter)
    T = T or episode_length(env_id)  # noqa: N806
    shared = _shared_params(root)
    count = shared.data.n_id + shared.data.n_ood
    try:
        cut = recorded.streams(data, T, count)
    except ConfigError as error:
        raise ConfigError(f"--dataset: {error}") from None
    support = {
        name: None if shared.injector_class(name).mode == "posthoc" else recorded.NO_SIMULATOR
        for name in shared.benchmark.injectors
    }
    if None not in support.values():
        raise ConfigError(
            f"--dataset: the shared benchmark.injectors ({', '.join(support)}) has no post-hoc "
            "fault, the only kind a pipeline of recorded data runs."
        )
    # The online faults' blocks are written although those faults are left out: check_params
    # checks every block against the environment (the shared ones name LunarLander's actions).
    blocks, _ = injector_blocks(adapter, cut.arrays["actions"][0], T)
    train_config = {
        "env_id": env_id,
        "file": dataset_id,
        "sha256": recorded.files_sha256(data_dir),
        "source": recorded.SOURCE,
    }
    note = f"the recording (a {recorded.SOURCE}): no policy runs here"
    params = params_text(directory.name, env_id, T, train_config, support, blocks, note,
                         recording=dataset_id)  # fmt: skip
    with _staged(directory, root) as staging:
        recorded.copy(data_dir, staging / recorded.DATASET_DIR)
        _write_params(staging, params, faults_text(env_id, support))
    used = int(cut.seeds[-1] + cut.arrays["episode_index"][-1, -1]) + 1
    recording = (
        f"recorded data {dataset_id} ({data.total_episodes} episodes, {data.total_steps} steps; "
        f"the first {used} make the {count} streams)"
    )
    return NewPipeline(directory, env_id, T, *_split(support), None, recording)


def _recorded_env(dataset_id: str, recorded_on: str | None, env_id: str | None) -> str:
    """The environment of a recorded pipeline: the one the dataset names, or --env."""
    if recorded_on is None and env_id is None:
        raise ConfigError(
            f"--env: {dataset_id} records no environment (env_spec); name the one it was "
            "recorded on (a Gymnasium id)."
        )
    if recorded_on is not None and env_id is not None and env_id != recorded_on:
        raise ConfigError(f"--env: {dataset_id} was recorded on {recorded_on}, not {env_id}.")
    return env_id or recorded_on


def _shared_params(root: Path) -> Params:
    """The shared protocol new pipelines extend (structure checked; components later)."""
    from oodrl.config import load_params
    from oodrl.suite.pipeline import PARAMS_FILE

    return load_params(root / PARAMS_FILE, components=False)


@contextmanager
def _staged(directory: Path, root: Path) -> Iterator[Path]:
    """A staging folder beside `directory` to fill; then its params are checked, it is given
    its DVC files and moved into place by one rename. A failure or an interruption (SIGINT,
    SIGTERM, SIGHUP) before that rename removes the staging folder, so `directory` is complete
    or absent; other processes never see a half-made pipeline under its name."""
    directory.parent.mkdir(parents=True, exist_ok=True)
    remove_dead(directory.parent, STAGING_PATTERN)
    staging = directory.with_name(f".{directory.name}.new-{os.getpid()}")
    with _signals_end_staging():
        try:
            # Inside the try: a signal handled just after mkdir returns still removes it.
            staging.mkdir()
            yield staging
            _check(staging)
            # Rendered in the staging folder: a sibling of `directory`, so every path the
            # DVC files hold (relative to the pipeline's folder) is the same there.
            _write_dvc_files(staging, root)
            if directory.exists():  # made meanwhile by another `oodrl new`: never replaced
                _check_name(directory.name, directory)
            staging.rename(directory)
        except BaseException:
            # A second signal must not cut the cleanup short (the handlers return after).
            _ignore_signals()
            shutil.rmtree(staging, ignore_errors=True)
            raise


@contextmanager
def _signals_end_staging() -> Iterator[None]:
    """SIGTERM and SIGHUP raise SystemExit(128 + signal) in the block, as SIGINT raises
    KeyboardInterrupt, so the staging folder's cleanup runs, where they would end the process
    at once (their default action). A caller's own handler is kept (oodrl's CLI raises
    KeyboardInterrupt for them), and so is an ignored signal (`nohup`). Every previous handler,
    SIGINT's too (the cleanup ignores it), is restored after; only the main thread has them."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def end(signum: int, frame: Any) -> None:
        raise SystemExit(128 + signum)

    # None: a handler set outside Python, which cannot be set back; such a signal is left be.
    kept = {number: signal.getsignal(number) for number in (signal.SIGINT, *ENDING_SIGNALS)}
    kept = {number: handler for number, handler in kept.items() if handler is not None}
    for number in ENDING_SIGNALS:
        if kept.get(number) == signal.SIG_DFL:
            signal.signal(number, end)
    try:
        yield
    finally:
        for number, handler in kept.items():
            signal.signal(number, handler)


def _ignore_signals() -> None:
    """While the staging folder is removed (`_signals_end_staging` restores the handlers)."""
    if threading.current_thread() is threading.main_thread():
        for number in (signal.SIGINT, *ENDING_SIGNALS):
            if signal.getsignal(number) is not None:
                signal.signal(number, signal.SIG_IGN)


def _write_params(staging: Path, params: str, faults: str) -> None:
    from oodrl.suite.pipeline import PARAMS_FILE

    (staging / PARAMS_FILE).write_text(params)
    (staging / "faults.yaml").write_text(faults)


def _split(support: dict[str, str | None]) -> tuple[tuple[str, ...], dict[str, str]]:
    """The supported faults, and each left out with its reason."""
    supported = tuple(n for n, reason in support.items() if reason is None)
    return supported, {n: reason for n, reason in support.items() if reason is not None}


def fault_support(adapter: EnvironmentAdapter, injectors: list[str]) -> dict[str, str | None]:
    """Each injector → None where the environment supports it, else the reason it is left out.

    Dynamics faults (`ScalingInjector`s) need the state vector; every other fault needs only
    observations and actions, which every environment has. The suite's own adapters have a
    tested state vector (tests/envs/test_adapters.py); a generic one is probed here.
    """
    from oodrl.envs.generic import GenericAdapter, probe_state
    from oodrl.injectors import INJECTORS
    from oodrl.injectors.online import ScalingInjector

    dynamics = [n for n in injectors if issubclass(INJECTORS.get(n), ScalingInjector)]
    probed = dynamics and isinstance(adapter, GenericAdapter)
    reason = probe_state(adapter) if probed else None
    return {name: reason if name in dynamics else None for name in injectors}


def _check_name(name: str, directory: Path) -> None:
    from oodrl.suite.pipeline import SUITE_DIR

    if not NAME_PATTERN.fullmatch(name):
        raise ConfigError(
            f"NAME: {name!r} is not a pipeline name; use lower-case letters, digits and _, "
            "starting with a letter (e.g. my_agent)."
        )
    if directory.exists() or directory.name == SUITE_DIR.name:
        raise ConfigError(
            f"NAME: {directory} exists already; choose another name (or remove it first)."
        )


def _adapter(env_id: str):
    """The environment's adapter, refused in one line for an unknown id or observation."""
    from oodrl.envs import ENVIRONMENTS

    try:
        adapter = ENVIRONMENTS.get(env_id)()
        adapter.state_dim  # noqa: B018 - makes the environment: its observation space is checked
        adapter.action_kind  # noqa: B018
    except OodrlError as error:
        raise ConfigError(f"--env: {error}") from None
    return adapter


def _check_env_id(env_id: str) -> None:
    """Refuse Gymnasium's `module:EnvId` (make EnvId after importing `module`, which registers
    it): oodrl reads `module:Class` as an adapter's import path, and its stages make env.id
    without importing anything, so such an environment is not one they could make."""
    from oodrl.envs import gymnasium_id

    module, colon, _ = gymnasium_id(env_id).partition(":")
    if colon:
        raise ConfigError(
            f"--env: {env_id!r} is Gymnasium's module:EnvId form, which oodrl does not support "
            f"(its stages make env.id without importing {module}); give an id that `import "
            "gymnasium` registers, e.g. CartPole-v1."
        )


def _observation_space(env_id: str):
    """The observation space of a Gymnasium id, or None for an id not in its registry (the
    adapter's lookup then names the closest one)."""
    import gymnasium

    if env_id not in gymnasium.registry:
        return None
    env = gymnasium.make(env_id)
    try:
        return env.observation_space
    finally:
        env.close()


def _image_spaces(space) -> Iterator[Any]:
    """The image observations in `space` (Dict and Tuple searched): a Box of 3 or more axes
    (height, width, channels...), or of 2 axes of uint8 pixels (a grayscale frame). A float
    Box of 2 axes is a table of features, which --flatten serves."""
    from gymnasium import spaces

    if isinstance(space, spaces.Box):
        shape = space.shape
        if len(shape) >= 3 or (len(shape) == 2 and space.dtype == np.uint8):
            yield space
    elif isinstance(space, spaces.Dict | spaces.Tuple):
        for part in space.spaces.values() if isinstance(space, spaces.Dict) else space.spaces:
            yield from _image_spaces(part)


def _refuse_images(env_id: str) -> None:
    """Refuse image observations, --flatten or not: a detector given every pixel as a feature
    (CarRacing: 27,648) measures nothing useful, and oodrl extracts no features from images."""
    image = next(_image_spaces(_observation_space(env_id)), None)
    if image is not None:
        raise ConfigError(
            f"--env: {env_id} observes images ({image}); oodrl's detectors take flat feature "
            "vectors, and image observations would need a feature extractor, which oodrl does "
            "not support."
        )


def _flattened(env_id: str) -> str:
    """The name of `env_id` with flattened observations; refused where they are flat."""
    from gymnasium import spaces

    from oodrl.envs import ENVIRONMENTS, flattened

    try:
        ENVIRONMENTS.path(env_id)  # an unknown id: the usual line, naming the closest one
    except OodrlError as error:
        raise ConfigError(f"--env: {error}") from None
    space = _observation_space(env_id)
    if isinstance(space, spaces.Box) and len(space.shape) == 1:
        raise ConfigError(f"--flatten: {env_id} observes a flat Box already; leave it out.")
    return flattened(env_id)


def episode_length(env_id: str) -> int:
    """The environment's registered episode length (max_episode_steps): the protocol's T."""
    import gymnasium

    from oodrl.envs import gymnasium_id

    steps = gymnasium.spec(gymnasium_id(env_id)).max_episode_steps
    if not steps:
        raise ConfigError(
            f"--env: {env_id} registers no episode length (max_episode_steps); give --T."
        )
    return int(steps)


def _make_policy(
    policy: str | None,
    train: str | None,
    env_id: str,
    models: Path,
    *,
    steps: int,
    episodes: int,
    seed: int,
) -> dict[str, Any]:
    """Write models/policy.pt and models/policy.json; return the report."""
    from oodrl.policies import convert

    out, report = models / "policy.pt", models / "policy.json"
    kwargs = {"episodes": episodes, "seed": EVALUATION_SEED}
    if train is not None:
        if train not in convert.TRAINERS:
            raise ConfigError(f"--train: {train!r}; allowed: {', '.join(convert.TRAINERS)}.")
        # The SB3 model stays beside the policy: what it was converted from.
        zip_path = convert.train_sb3(train, env_id, steps, seed, models / f"sb3_{train}.zip")
        how = f"oodrl new --train {train} --steps {steps} --seed {seed}"
        source = convert.Sb3Source(zip_path, None, "Stable-Baselines3 .zip")
        return convert.convert_sb3(source, env_id, out, report, how=how, **kwargs)
    path = Path(policy)
    if not path.exists() and ":" in policy:
        return convert.save_callable(policy, env_id, out, report, **kwargs)
    if path.is_file() and not zipfile_like(path):
        return convert.convert_checkpoint(path, env_id, out, report, **kwargs)
    source = convert.find_source(path)
    if source.env_id is not None and source.env_id != env_id:
        raise ConfigError(
            f"--policy: {path} is an RL Zoo run on {source.env_id}; --env says {env_id}."
        )
    return convert.convert_sb3(source, env_id, out, report, **kwargs)


def _check_beats_random(
    report: dict[str, Any], adapter: EnvironmentAdapter, steps: int | None
) -> None:
    """Refuse a policy no better than uniformly random actions: every impact stage would fail
    after collection (R̃ = (R − R_rand) / (R_clean − R_rand) needs R_clean > R_rand,
    `oodrl.protocol.impact`). Random actions are scored on the evaluation's own episodes: episode i
    resets from seed EVALUATION_SEED + i and draws its actions from numpy's generator of it.

    The rule: the policy's mean return must exceed random's mean by more than two standard
    errors of random's mean (its std / √n; none from one episode), so a policy whose return
    random actions reach by chance on these episodes is not taken for a trained one."""
    from oodrl.policies.evaluate import evaluate_policy
    from oodrl.protocol.impact import UniformRandomPolicy

    evaluation = report["evaluation"]
    episodes, mean = int(evaluation["episodes"]), float(evaluation["mean"])
    rngs = [np.random.default_rng(EVALUATION_SEED + i) for i in range(episodes)]
    chance = evaluate_policy(
        UniformRandomPolicy(adapter), episodes, EVALUATION_SEED, env_id=adapter.env_id, rngs=rngs
    )
    margin = 2 * float(chance.std(ddof=1)) / np.sqrt(episodes) if episodes > 1 else 0.0
    if not mean > chance.mean() + margin:
        option, advice = (
            ("--policy", "train it longer")
            if steps is None
            else ("--train", f"train longer (--steps, now {steps})")
        )
        raise PolicyError(
            f"{option}: the policy's mean return {mean:.1f} over {episodes} held-out "
            f"episodes is not above a uniformly random policy's ({chance.mean():.1f}, + "
            f"{margin:.1f} for its noise) on the same episodes, so no fault's impact can be "
            f"measured against it; {advice}."
        )


def zipfile_like(path: Path) -> bool:
    """Whether a file is a zip archive (an SB3 model; torch checkpoints are zips too, told
    apart by SB3's `data` entry)."""
    import zipfile

    if not zipfile.is_zipfile(path):
        return False
    with zipfile.ZipFile(path) as archive:
        return "data" in archive.namelist()


def injector_blocks(
    adapter,
    actions: np.ndarray,
    T: int,  # noqa: N803
) -> tuple[dict[str, dict], str | None]:
    """The injector parameters this environment and the clean `actions` of one stream need,
    and why the action predicate is left out (None when it is in)."""
    from oodrl.core.spec import default_onset

    ramp = max(1, round(RAMP_SHARE * (T - default_onset(T))))
    predicate, reason = action_predicate(adapter, actions)
    return {PREDICATE_FAULT: predicate, "gradual_drift": {"ramp_steps": ramp}}, reason


def action_predicate(adapter, actions: np.ndarray) -> tuple[dict[str, Any], str | None]:
    """`action_conditioned_dynamics`'s predicate from clean actions: the discrete action, or
    the coordinate and threshold, holding closest to PREDICATE_SHARE of steps; with the reason
    it is left out when none holds on some steps and not on others."""
    if adapter.action_kind == "discrete":
        shares = np.bincount(actions, minlength=adapter.action_size) / len(actions)
        best = int(np.argmin(np.abs(shares - PREDICATE_SHARE)))
        block = {"target_action": best, "target_dim": None, "target_threshold": None}
        if 0 < shares[best] < 1:
            return block, None
        return block, "the policy commands one action on every clean step: no action predicate."
    for dim in range(adapter.action_size):
        column = actions[:, dim].astype(np.float64)
        threshold = float(np.format_float_positional(np.quantile(column, 1 - PREDICATE_SHARE), 4))
        low, high = float(adapter.action_low[dim]), float(adapter.action_high[dim])
        if low <= threshold < high and 0 < np.mean(column > threshold) < 1:
            return {"target_action": None, "target_dim": dim, "target_threshold": threshold}, None
    middle = float(np.clip(0.0, adapter.action_low[0], np.nextafter(adapter.action_high[0], -1)))
    block = {"target_action": None, "target_dim": 0, "target_threshold": middle}
    return block, "the policy's clean actions never cross a threshold: no action predicate."


def _flow(value: Any) -> str:
    """A value as one line of YAML (JSON is YAML's flow style)."""
    return json.dumps(value)


def params_text(
    name: str,
    env_id: str,
    T: int,  # noqa: N803
    train_config: dict[str, Any],
    support: dict[str, str | None],
    blocks: dict[str, dict],
    train_note: str,
    recording: str | None = None,
) -> str:
    """params.yaml of the new pipeline: only what differs from the shared protocol."""
    from oodrl.core.spec import default_onset

    supported = [n for n, reason in support.items() if reason is None]
    if recording is None:
        header = [
            f"# {name}: {env_id}, made by `oodrl new` (SPEC §18): what differs from the shared",
            "# ../../params.yaml. faults.yaml lists the faults left out and why.",
        ]
    else:
        header = [
            f"# {name}: recorded data, {recording} on {env_id}, made by `oodrl new --dataset`",
            "# (SPEC §18): what differs from the shared ../../params.yaml. faults.yaml lists the",
            "# faults left out and why.",
        ]
    lines = [
        *header,
        "extends: ../../params.yaml",
        "",
        "env:",
        f"  id: {env_id}",
        f"  T: {T}".ljust(30) + f"# steps per stream ({_length_note(env_id, T)})",
        "  onset: null".ljust(30) + f"# floor(T/3) = {default_onset(T)}",
        "",
        "policy:",
        "  train:".ljust(30) + f"# {train_note}",
        "    algorithm: imported",
        *(f"    {key}: {_flow(value)}" for key, value in sorted(train_config.items())),
        "",
    ]
    if len(supported) < len(support):
        lines += ["benchmark:", f"  injectors: {_flow(supported)}", ""]
    lines += [
        "anomaly:",
        "  injectors:",
        *(f"    {key}: {_flow(block)}" for key, block in sorted(blocks.items())),
    ]
    return "\n".join(lines) + "\n"


def _length_note(env_id: str, T: int) -> str:  # noqa: N803
    import gymnasium

    from oodrl.envs import gymnasium_id

    length = gymnasium.spec(gymnasium_id(env_id)).max_episode_steps
    if not length:
        return "--T; episodes have no time limit"
    return "the episode length" if length == T else f"--T; episodes last up to {length}"


def faults_text(env_id: str, support: dict[str, str | None]) -> str:
    from oodrl.io import yamlio

    header = f"# The shared protocol's faults on {env_id} (oodrl new, SPEC §18).\n"
    return header + yamlio.dump(
        {
            "supported": [n for n, reason in support.items() if reason is None],
            "left_out": {n: reason for n, reason in support.items() if reason is not None},
        }
    )


def _check(directory: Path) -> None:
    """The new params validate, components and environment included (as check_params does)."""
    from oodrl.config import load_params
    from oodrl.suite.params_check import check_completely

    try:
        check_completely(load_params(directory / "params.yaml"))
    except ContractError as error:
        raise ConfigError(str(error)) from None


def _write_dvc_files(directory: Path, root: Path) -> None:
    from oodrl.suite.pipeline import pipeline_files, subrepo_files

    files = {**pipeline_files(directory, root), **subrepo_files(directory, root)}
    for path, text in files.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def summary(made: NewPipeline, root: Path) -> str:
    """What `oodrl new` tells its user: where, what the policy scored (or which data it has),
    which faults run."""
    where = made.directory.relative_to(root)
    if made.policy_report is None:
        source = made.recording
    else:
        evaluation = made.policy_report["evaluation"]
        source = (
            f"policy mean return {evaluation['mean']:.1f} over {evaluation['episodes']} "
            "held-out episodes"
        )
    lines = [
        f"{where}: {made.env_id}, T={made.T}; {source}",
        f"faults: {', '.join(made.supported)}",
        *(
            f"left out: {', '.join(n for n, r in made.left_out.items() if r == reason)}: {reason}"
            for reason in dict.fromkeys(made.left_out.values())
        ),
        f"next: (cd {where} && dvc repro), then oodrl show {where}/reports/results.yaml",
    ]
    return "\n".join(lines)
