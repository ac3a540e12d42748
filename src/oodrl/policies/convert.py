"""Policies people have, as oodrl's machine-independent checkpoint (SPEC §18).

- A Stable-Baselines3 ``.zip`` of PPO, A2C, DQN, SAC or TD3 with an MLP policy, with the
  ``VecNormalize`` statistics of its training when a ``vecnormalize.pkl`` lies beside it.
- An RL Zoo run folder (``logs/<algo>/<env>_<n>/``, as rl-zoo3 writes it): ``<env>.zip``, and
  ``<env>/vecnormalize.pkl`` and ``<env>/config.yml`` beside it.

The network's deterministic path becomes an ``oodrl.policies.act`` architecture: DQN's
Q-network acts by argmax (``mlp``); PPO and A2C by the argmax of their logits (``mlp``) or the
Gaussian's mean clipped to the action bounds (``clipped_actor``), through their tanh layers;
SAC and TD3 by their tanh-squashed actor (``tanh_actor``). The observation statistics are
applied first, as VecNormalize does. It then acts as SB3's ``predict(deterministic=True)`` on
the normalised observation, up to rounding: SB3 sums in torch's float32 kernels, oodrl rounds
each layer's exact result once (`oodrl.numerics`), so continuous actions agree to within
``ACTION_TOLERANCE`` of the action range and discrete ones wherever the best two outputs differ
by more than ``ARGMAX_MARGIN`` (tests/policies/test_convert.py checks both on 2,000
observations).

Everything else acts through a ``module:function`` callable (`oodrl.policies.load`), which
oodrl cannot certify machine-independent.
"""

from __future__ import annotations

import hashlib
import pickle
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from oodrl.errors import PolicyError
from oodrl.policies.load import SB3_ALGORITHMS, _load_sb3, _sb3_algorithm, quiet_sb3_logger

#: Largest difference from SB3's continuous action, as a share of the action range.
ACTION_TOLERANCE = 1e-5
#: Smallest gap between SB3's best two outputs beyond which the argmax agrees.
ARGMAX_MARGIN = 1e-4
VECNORMALIZE = "vecnormalize.pkl"
ZOO_CONFIG = "config.yml"
#: How PyYAML dumps the OrderedDict RL Zoo saves its hyperparameters as.
ORDERED_DICT_TAG = "tag:yaml.org,2002:python/object/apply:collections.OrderedDict"


@dataclass(frozen=True)
class Sb3Source:
    """Where a Stable-Baselines3 model and its normalisation come from."""

    model: Path
    vecnormalize: Path | None
    kind: str  # 'Stable-Baselines3 <ALGO> .zip' or 'RL Zoo folder'
    env_id: str | None = None  # the RL Zoo folder names it


def find_source(path: Path) -> Sb3Source:
    """The model and statistics of a ``.zip`` or an RL Zoo folder; a one-line error otherwise."""
    if path.is_dir():
        return _zoo_source(path)
    if not path.is_file():
        raise PolicyError(f"{path}: no such file or folder.")
    beside = path.with_name(VECNORMALIZE)
    return Sb3Source(path, beside if beside.is_file() else None, "Stable-Baselines3 .zip")


def _zoo_source(folder: Path) -> Sb3Source:
    """RL Zoo's ``<env>_<n>/``: the final ``<env>.zip`` and the folder ``<env>/`` of its
    settings (config.yml, vecnormalize.pkl)."""
    runs = sorted(z for z in folder.glob("*.zip") if (folder / z.stem / ZOO_CONFIG).is_file())
    if len(runs) != 1:
        raise PolicyError(
            f"{folder} is not an RL Zoo run folder: expected one <env>.zip beside a folder "
            f"<env>/ holding {ZOO_CONFIG} (as rl-zoo3 writes logs/<algo>/<env>_<n>/)."
        )
    model = runs[0]
    settings = folder / model.stem
    _check_zoo_config(settings / ZOO_CONFIG)
    stats = settings / VECNORMALIZE
    return Sb3Source(model, stats if stats.is_file() else None, "RL Zoo folder", model.stem)


def _check_zoo_config(path: Path) -> None:
    """Refuse what oodrl cannot replay: environment wrappers and frame stacking change the
    observations the policy was trained on, and a non-MLP policy has no oodrl network."""
    config = read_zoo_config(path)
    if config.get("env_wrapper"):
        raise PolicyError(
            f"{path}: the agent was trained inside env_wrapper {config['env_wrapper']!r}; oodrl "
            "runs the environment unwrapped, so its observations would differ."
        )
    if config.get("frame_stack"):
        raise PolicyError(f"{path}: frame_stack is not supported (one observation per step).")
    policy = config.get("policy", "MlpPolicy")
    if policy != "MlpPolicy":
        raise PolicyError(f"{path}: policy {policy!r}; oodrl converts MlpPolicy networks only.")


def read_zoo_config(path: Path) -> dict[str, Any]:
    """RL Zoo's config.yml: an OrderedDict dumped by PyYAML, read without running any code."""
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    def ordered_dict(loader: yaml.SafeLoader, node: yaml.Node) -> dict[str, Any]:
        (pairs,) = loader.construct_sequence(node, deep=True)
        return {str(k): v for k, v in pairs}

    Loader.add_constructor(ORDERED_DICT_TAG, ordered_dict)
    try:
        data = yaml.load(path.read_text(), Loader=Loader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as error:
        raise PolicyError(f"{path}: not an RL Zoo config.yml ({type(error).__name__}).") from None
    if not isinstance(data, dict):
        raise PolicyError(f"{path}: not an RL Zoo config.yml (expected a mapping).")
    return data


def normalization(path: Path | None) -> dict[str, Any] | None:
    """VecNormalize's observation statistics as an architecture's ``observation_normalization``
    (None without a file, or when it normalised rewards alone)."""
    if path is None:
        return None
    try:
        with path.open("rb") as file:
            stats = pickle.load(file)  # noqa: S301 - the user's own VecNormalize file
    except Exception as error:  # unpickling fails in many ways on a foreign file
        raise PolicyError(f"{path}: not a VecNormalize file ({type(error).__name__}).") from None
    # Its own attributes, not getattr: an unpickled VecNormalize wraps no environment, and its
    # __getattr__ asks that missing one for any attribute it lacks, recursing without end
    # (SB3 sets no obs_rms when it normalised rewards alone).
    own = getattr(stats, "__dict__", {})
    if "clip_obs" in own and not own.get("norm_obs", True):
        return None  # it normalised rewards alone
    if "obs_rms" not in own or "clip_obs" not in own:
        raise PolicyError(f"{path}: not a VecNormalize file (no observation statistics).")
    if isinstance(stats.obs_rms, dict):
        raise PolicyError(f"{path}: normalises a Dict observation; oodrl needs a flat Box.")
    return {
        "mean": [float(v) for v in np.asarray(stats.obs_rms.mean, np.float64).ravel()],
        "var": [float(v) for v in np.asarray(stats.obs_rms.var, np.float64).ravel()],
        "epsilon": float(stats.epsilon),
        "clip": float(stats.clip_obs),
    }


# -- the network ------------------------------------------------------------------------------
def _linear_stack(modules: list[Any], where: str) -> tuple[list[Any], str | None]:
    """The Linear layers of Linear/activation/…/Linear modules and their one activation."""
    import torch

    names = {torch.nn.ReLU: "relu", torch.nn.Tanh: "tanh"}
    linears, activations = [], set()
    for module in modules:
        if isinstance(module, torch.nn.Linear):
            linears.append(module)
        elif type(module) in names:
            activations.add(names[type(module)])
        else:
            raise PolicyError(
                f"{where} has a {type(module).__name__} layer; oodrl converts Linear layers "
                "with ReLU or Tanh between them."
            )
    if len(activations) > 1:
        raise PolicyError(f"{where} mixes activations {sorted(activations)}.")
    return linears, (activations.pop() if activations else None)


def _check_flat(extractor: Any, algorithm: str) -> None:
    from stable_baselines3.common.torch_layers import FlattenExtractor

    if not isinstance(extractor, FlattenExtractor):
        raise PolicyError(
            f"SB3 {algorithm} uses {type(extractor).__name__}; oodrl converts MlpPolicy "
            "networks (a FlattenExtractor over a flat Box observation)."
        )


def sb3_network(model: Any, algorithm: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(architecture, state_dict)`` of an SB3 model's deterministic action."""
    import gymnasium as gym

    policy = model.policy
    if getattr(model, "use_sde", False):
        raise PolicyError(f"SB3 {algorithm} with use_sde=True is not supported.")
    space = model.action_space
    if algorithm == "DQN":
        _check_flat(policy.q_net.features_extractor, algorithm)
        linears, activation = _linear_stack(list(policy.q_net.q_net), "DQN's q_net")
        kind = "mlp"
    elif algorithm in ("PPO", "A2C"):
        _check_flat(policy.pi_features_extractor, algorithm)
        linears, activation = _linear_stack(
            [*policy.mlp_extractor.policy_net, policy.action_net], f"{algorithm}'s actor"
        )
        kind = "mlp" if isinstance(space, gym.spaces.Discrete) else "clipped_actor"
    elif algorithm == "SAC":
        _check_flat(policy.actor.features_extractor, algorithm)
        linears, activation = _linear_stack([*policy.actor.latent_pi, policy.actor.mu], "actor")
        kind = "tanh_actor"
    elif algorithm == "TD3":
        _check_flat(policy.actor.features_extractor, algorithm)
        modules = list(policy.actor.mu)
        import torch

        if not modules or not isinstance(modules[-1], torch.nn.Tanh):
            raise PolicyError("TD3's actor does not end in tanh (squash_output).")
        linears, activation = _linear_stack(modules[:-1], "TD3's actor")
        kind = "tanh_actor"
    else:
        raise PolicyError(f"SB3 {algorithm}: oodrl converts {', '.join(SB3_ALGORITHMS)}.")
    if kind != "mlp" and not isinstance(space, gym.spaces.Box):
        raise PolicyError(f"SB3 {algorithm} with action space {space} is not supported.")
    state = {}
    for i, layer in enumerate(linears):
        state[f"net.{2 * i}.weight"] = layer.weight.detach().clone().contiguous()
        state[f"net.{2 * i}.bias"] = layer.bias.detach().clone().contiguous()
    architecture: dict[str, Any] = {
        "kind": kind,
        "state_dim": int(np.prod(model.observation_space.shape)),
        "hidden_sizes": [int(layer.out_features) for layer in linears[:-1]],
        "activation": activation or "relu",
    }
    if kind == "mlp":
        architecture["n_actions"] = int(space.n)
    else:
        architecture["action_dim"] = int(np.prod(space.shape))
        architecture["action_low"] = [float(x) for x in space.low]
        architecture["action_high"] = [float(x) for x in space.high]
    return architecture, state


def load_sb3(source: Sb3Source) -> tuple[Any, str]:
    """The SB3 model of a source and its algorithm's name."""
    algorithm = _sb3_algorithm(source.model.read_bytes())
    if algorithm is None or algorithm == "other":
        raise PolicyError(
            f"{source.model}: not a Stable-Baselines3 model of {', '.join(SB3_ALGORITHMS)}."
        )
    return _load_sb3(source.model, algorithm), algorithm


def convert_sb3(
    source: Sb3Source,
    env_id: str,
    policy_path: Path,
    report_path: Path,
    *,
    episodes: int = 10,
    seed: int = 1_000_000,
    how: str | None = None,
) -> dict[str, Any]:
    """Write the oodrl checkpoint of an SB3 model and its report (held-out returns over
    `episodes` episodes); return the report. `how` overrides the recorded source."""
    from oodrl.policies.settings import ImportedConfig

    started = time.perf_counter()
    model, algorithm = load_sb3(source)
    architecture, state = sb3_network(model, algorithm)
    stats = normalization(source.vecnormalize)
    if stats is not None:
        if len(stats["mean"]) != architecture["state_dim"]:
            raise PolicyError(
                f"{source.vecnormalize}: statistics of {len(stats['mean'])}-dim observations; "
                f"the model takes {architecture['state_dim']}."
            )
        architecture["observation_normalization"] = stats
    kind = source.kind.replace("Stable-Baselines3", f"Stable-Baselines3 {algorithm}")
    config = ImportedConfig(
        env_id=env_id,
        source=how or kind,
        file=source.model.name,
        sha256=hashlib.sha256(source.model.read_bytes()).hexdigest(),
    )
    return save_imported(
        policy_path,
        report_path,
        architecture,
        state,
        config,
        episodes=episodes,
        seed=seed,
        steps_run=int(getattr(model, "num_timesteps", 0)),
        started=started,
        trainer={"stable_baselines3": _sb3_version(), "algorithm": algorithm},
    )


def save_imported(
    policy_path: Path,
    report_path: Path,
    architecture: dict[str, Any],
    state: dict[str, Any],
    config: Any,
    *,
    episodes: int,
    seed: int,
    steps_run: int,
    started: float,
    trainer: dict[str, str],
) -> dict[str, Any]:
    """Evaluate the converted policy on held-out seeds and save it with its report."""
    from oodrl.envs import ENVIRONMENTS
    from oodrl.policies.act import policy_from_checkpoint
    from oodrl.policies.checkpoint import save_policy
    from oodrl.policies.evaluate import evaluate_policy

    policy = policy_from_checkpoint(architecture, state)
    ENVIRONMENTS.get(config.env_id)().check_policy(policy)
    returns = evaluate_policy(policy, episodes, seed, env_id=config.env_id)
    return save_policy(
        policy_path,
        report_path,
        architecture=architecture,
        state_dict=state,
        env_id=config.env_id,
        train_config=config.as_dict(),
        final_returns=returns,
        final_eval_seed=seed,
        tuning={"best_step": steps_run},
        steps_run=steps_run,
        learning_curve=[],
        wall_time_s=time.perf_counter() - started,
        trainer=trainer,
    )


def _sb3_version() -> str:
    import stable_baselines3

    return str(stable_baselines3.__version__)


def convert_checkpoint(
    path: Path, env_id: str, policy_path: Path, report_path: Path, *, episodes: int, seed: int
) -> dict[str, Any]:
    """An oodrl checkpoint made elsewhere, saved with this pipeline's imported settings."""
    import torch

    from oodrl.policies.checkpoint import CHECKPOINT_FORMAT
    from oodrl.policies.settings import ImportedConfig

    started = time.perf_counter()
    data = path.read_bytes()
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for foreign bytes
        raise PolicyError(
            f"{path}: not an oodrl checkpoint, a Stable-Baselines3 .zip or an RL Zoo folder "
            f"(torch.load: {type(error).__name__})."
        ) from None
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != CHECKPOINT_FORMAT:
        raise PolicyError(
            f"{path}: not an oodrl checkpoint, a Stable-Baselines3 .zip or an RL Zoo folder."
        )
    config = ImportedConfig(
        env_id=env_id,
        source="oodrl checkpoint",
        file=path.name,
        sha256=hashlib.sha256(data).hexdigest(),
    )
    return save_imported(
        policy_path,
        report_path,
        dict(checkpoint["architecture"]),
        dict(checkpoint["state_dict"]),
        config,
        episodes=episodes,
        seed=seed,
        steps_run=0,
        started=started,
        trainer={"algorithm": "imported"},
    )


def save_callable(
    function: str, env_id: str, policy_path: Path, report_path: Path, *, episodes: int, seed: int
) -> dict[str, Any]:
    """A ``module:function`` policy: its pointer as the policy file (SPEC §18: not certified
    machine-independent, its code is not hashed into the data), and its report."""
    import json

    from oodrl.envs import ENVIRONMENTS
    from oodrl.io.fileio import atomic_write_bytes
    from oodrl.policies.evaluate import evaluate_policy
    from oodrl.policies.load import CALLABLE_FORMAT, CallablePolicy
    from oodrl.policies.settings import ImportedConfig
    from oodrl.registry import import_path

    adapter = ENVIRONMENTS.get(env_id)()
    import_path(function)  # a missing module or function is one line now, not at collection
    spec = {
        "format": CALLABLE_FORMAT,
        "callable": function,
        "state_dim": adapter.state_dim,
        "action_kind": adapter.action_kind,
        "action_size": adapter.action_size,
        "certified_machine_independent": False,
    }
    data = (json.dumps(spec, indent=2, sort_keys=True) + "\n").encode()
    policy = CallablePolicy(spec, hashlib.sha256(data).hexdigest())
    returns = evaluate_policy(policy, episodes, seed, env_id=env_id)
    config = ImportedConfig(env_id=env_id, source="module:function callable", file=function)
    report = {
        "env_id": env_id,
        "certified_machine_independent": False,
        "train_config": config.as_dict(),
        "evaluation": {
            "mode": "greedy",
            "episodes": len(returns),
            "seeds": [seed + i for i in range(len(returns))],
            "returns": [float(r) for r in returns],
            "mean": float(returns.mean()),
            "std": float(returns.std()),
        },
    }
    atomic_write_bytes(policy_path, data)
    atomic_write_bytes(report_path, (json.dumps(report, indent=2, sort_keys=True) + "\n").encode())
    return report


#: `oodrl new --train`: the SB3 algorithm of each choice and the action kind it needs.
TRAINERS = {"sac": ("SAC", "continuous"), "ppo": ("PPO", None), "dqn": ("DQN", "discrete")}


def train_sb3(choice: str, env_id: str, steps: int, seed: int, out: Path) -> Path:
    """Train an SB3 MLP policy with the library's default settings; save its .zip at `out`."""
    import torch

    from oodrl.envs import ENVIRONMENTS, make

    algorithm, kind = TRAINERS[choice]
    adapter = ENVIRONMENTS.get(env_id)()
    if kind is not None and adapter.action_kind != kind:
        raise PolicyError(
            f"--train {choice}: {algorithm} needs {kind} actions; {env_id} has "
            f"{adapter.describe_actions()}. Use --train "
            f"{'dqn or ppo' if adapter.action_kind == 'discrete' else 'sac or ppo'}."
        )
    import stable_baselines3

    torch.set_num_threads(1)
    settings = {} if choice == "ppo" else {"buffer_size": max(1, min(steps, 1_000_000))}
    model = getattr(stable_baselines3, algorithm)(
        "MlpPolicy", make(env_id), seed=seed, device="cpu", verbose=0, **settings
    )
    model.set_logger(quiet_sb3_logger())
    model.learn(total_timesteps=steps)
    model.save(out)
    return out
