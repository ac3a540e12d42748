"""Load a policy from a file and roll it out.

Accepted files (``load_policy`` tells them apart by content, not by name):

- an oodrl checkpoint written by :func:`oodrl.policies.train.train` — a dict
  ``{"format": "oodrl-policy", "version": 1, "architecture": {...}, "state_dict": {...}, ...}``;
- a plain torch ``state_dict`` (or a dict ``{"state_dict": ...}``) together with an
  ``architecture`` argument naming the network: ``{"kind": "mlp", "hidden_sizes": [64, 64]}``
  (``nn.Sequential`` of Linear/ReLU; Q-values or logits, acted on by argmax) or
  ``{"kind": "noisy_dqn", "hidden_sizes": [...], "sigma0": 0.5}``;
- a Stable-Baselines3 ``.zip`` (DQN or PPO, read from the zip), loaded by SB3's own loader on CPU
  and acted on deterministically. stable-baselines3 is an optional dependency (``oodrl[sb3]``).

Every torch load uses ``weights_only=True``. A missing, corrupt or foreign file raises
:class:`oodrl.errors.PolicyError` with a one-line message.
"""

from __future__ import annotations

import abc
import hashlib
import io
import json
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from oodrl.errors import PolicyError
from oodrl.policies.networks import NoisyQNetwork, mlp

Mode = Literal["greedy", "noisy"]

CHECKPOINT_FORMAT = "oodrl-policy"
CHECKPOINT_VERSION = 1
ARCHITECTURE_KINDS = ("noisy_dqn", "mlp")
SB3_ALGORITHMS = ("DQN", "PPO")
ACCEPTED = (
    "accepted: an oodrl checkpoint (models/policy.pt), a torch state_dict with "
    f"architecture={{'kind': one of {list(ARCHITECTURE_KINDS)}, 'hidden_sizes': [...]}}, "
    f"or a Stable-Baselines3 {'/'.join(SB3_ALGORITHMS)} .zip"
)


class Policy(abc.ABC):
    """A discrete-action policy: ``act`` maps a batch of observations to one action per row."""

    kind: str
    mode: Mode
    state_dim: int
    n_actions: int
    sha256: str

    @abc.abstractmethod
    def act(self, obs: np.ndarray, rngs: Sequence[np.random.Generator] | None = None) -> np.ndarray:
        """Actions (n,) int64 for observations (n, state_dim) float32.

        ``rngs`` (one generator per row, i.e. per environment stream) is used only in ``noisy``
        mode, where row ``i`` draws its noise from ``rngs[i]`` alone.
        """


class QNetworkPolicy(Policy):
    """Argmax over the outputs of a torch network; NoisyNet noise per row in ``noisy`` mode."""

    def __init__(
        self, network: nn.Module, *, kind: str, mode: Mode = "greedy", sha256: str = ""
    ) -> None:
        if mode == "noisy" and not isinstance(network, NoisyQNetwork):
            raise PolicyError(f"mode 'noisy' needs a noisy_dqn network; {kind!r} has no noise")
        self.network = network.eval()
        self.kind = kind
        self.mode = mode
        self.sha256 = sha256
        first, last = _linear_shapes(network)
        self.state_dim, self.n_actions = first[1], last[0]

    def act(self, obs: np.ndarray, rngs: Sequence[np.random.Generator] | None = None) -> np.ndarray:
        x = torch.as_tensor(np.asarray(obs, dtype=np.float32).reshape(-1, self.state_dim))
        with torch.no_grad():
            if self.mode == "noisy":
                if rngs is None or len(rngs) != len(x):
                    raise ValueError("noisy mode needs one numpy Generator per observation row")
                q = self.network(x, self.network.row_noise(rngs))
            else:
                q = self.network(x)
        return q.argmax(dim=1).numpy().astype(np.int64)


class Sb3Policy(Policy):
    """A Stable-Baselines3 model acting deterministically (``predict(deterministic=True)``)."""

    def __init__(self, model: Any, *, kind: str, sha256: str) -> None:
        if not isinstance(model.action_space, gym.spaces.Discrete):
            raise PolicyError(f"{kind} model has action space {model.action_space}; need Discrete")
        self.model = model
        self.kind = kind
        self.mode = "greedy"
        self.sha256 = sha256
        self.state_dim = int(np.prod(model.observation_space.shape))
        self.n_actions = int(model.action_space.n)

    def act(self, obs: np.ndarray, rngs: Sequence[np.random.Generator] | None = None) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float32).reshape(-1, self.state_dim)
        actions, _ = self.model.predict(obs, deterministic=True)
        return np.asarray(actions, dtype=np.int64).reshape(-1)


def build_network(architecture: Mapping[str, Any], state_dim: int, n_actions: int) -> nn.Module:
    """The untrained network an ``architecture`` mapping names."""
    kind = architecture.get("kind")
    hidden_sizes = [int(h) for h in architecture.get("hidden_sizes", (64, 64))]
    if kind == "noisy_dqn":
        sigma0 = float(architecture.get("sigma0", 0.5))
        return NoisyQNetwork(state_dim, n_actions, hidden_sizes, sigma0)
    if kind == "mlp":
        return mlp(state_dim, n_actions, hidden_sizes)
    raise PolicyError(
        f"unknown architecture kind {kind!r}; known kinds: {list(ARCHITECTURE_KINDS)}"
    )


def load_policy(
    path: str | Path,
    mode: Mode = "greedy",
    architecture: Mapping[str, Any] | None = None,
    state_dim: int | None = None,
    n_actions: int | None = None,
) -> Policy:
    """Load the policy stored at ``path`` (see the module docstring for the accepted files).

    ``architecture`` is needed only for a plain state_dict; ``state_dim`` and ``n_actions`` are
    checked against the network when given (else read from its first and last layers).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise PolicyError(f"cannot read policy file {path}: {exc.strerror or exc}") from None
    if mode not in ("greedy", "noisy"):
        raise PolicyError(f"policy mode must be 'greedy' or 'noisy'; got {mode!r}")
    sha256 = hashlib.sha256(data).hexdigest()
    sb3_algorithm = _sb3_algorithm(data)
    if sb3_algorithm == "other":
        raise PolicyError(
            f"{path} is a Stable-Baselines3 model of an unsupported algorithm; {ACCEPTED}"
        )
    if sb3_algorithm is not None:
        if mode == "noisy":
            raise PolicyError(
                f"{path}: mode 'noisy' needs a noisy_dqn network, not SB3 {sb3_algorithm}"
            )
        policy: Policy = Sb3Policy(
            _load_sb3(path, sb3_algorithm), kind=f"sb3_{sb3_algorithm.lower()}", sha256=sha256
        )
    else:
        policy = _load_torch(path, data, mode, architecture, sha256)
    _check_dims(path, policy, state_dim, n_actions)
    return policy


def _load_torch(
    path: Path,
    data: bytes,
    mode: Mode,
    architecture: Mapping[str, Any] | None,
    sha256: str,
) -> Policy:
    try:
        obj = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for foreign bytes; all mean "not ours"
        if "Weights only load failed" in str(exc):
            reason = "it pickles Python objects, which weights_only=True refuses; save a state_dict"
        else:
            reason = f"torch.load: {type(exc).__name__}"
        raise PolicyError(f"{path} is not a loadable policy file ({reason}); {ACCEPTED}") from None
    if isinstance(obj, Mapping) and obj.get("format") == CHECKPOINT_FORMAT:
        if obj.get("version") != CHECKPOINT_VERSION:
            raise PolicyError(
                f"{path}: oodrl checkpoint version {obj.get('version')!r} is not supported "
                f"(this oodrl reads version {CHECKPOINT_VERSION})"
            )
        architecture, state_dict = obj["architecture"], obj["state_dict"]
    elif isinstance(obj, Mapping) and architecture is not None:
        state_dict = obj.get("state_dict", obj)
    elif isinstance(obj, Mapping):
        raise PolicyError(
            f"{path} holds a plain state_dict; pass architecture={{'kind': one of "
            f"{list(ARCHITECTURE_KINDS)}, 'hidden_sizes': [...]}} to load it"
        )
    else:
        raise PolicyError(f"{path} holds a {type(obj).__name__}, not a policy; {ACCEPTED}")
    kind = architecture.get("kind")
    if kind not in ARCHITECTURE_KINDS:
        raise PolicyError(
            f"{path}: unknown architecture kind {kind!r}; known kinds: {list(ARCHITECTURE_KINDS)}"
        )
    if mode == "noisy" and kind != "noisy_dqn":
        raise PolicyError(f"{path}: mode 'noisy' needs a noisy_dqn network, not {kind!r}")
    state_dict = _strip_common_prefix(state_dict)
    dims = _state_dict_dims(path, state_dict)
    network = build_network(architecture, *dims)
    try:
        network.load_state_dict(state_dict)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        detail = first[1].strip() if len(first) > 1 else first[0]
        raise PolicyError(
            f"{path}: weights do not fit architecture {dict(architecture)} ({detail})"
        ) from None
    return QNetworkPolicy(network, kind=str(architecture["kind"]), mode=mode, sha256=sha256)


def _state_dict_dims(path: Path, state_dict: Mapping[str, Any]) -> tuple[int, int]:
    """``(state_dim, n_actions)`` read from the first and last weight matrices."""
    matrices = [
        v
        for k, v in state_dict.items()
        if isinstance(v, torch.Tensor) and v.ndim == 2 and not k.endswith("weight_sigma")
    ]
    if not matrices:
        raise PolicyError(f"{path}: no weight matrices in the state_dict; {ACCEPTED}")
    return int(matrices[0].shape[1]), int(matrices[-1].shape[0])


def _strip_common_prefix(state_dict: Mapping[str, Any]) -> dict[str, Any]:
    """Drop a prefix shared by every key (``net.``, ``q_net.``, ``module.``) from a state_dict."""
    keys = list(state_dict)
    for prefix in ("module.", "q_net.", "net.", "model."):
        if keys and all(k.startswith(prefix) for k in keys):
            return _strip_common_prefix({k[len(prefix) :]: v for k, v in state_dict.items()})
    return dict(state_dict)


def _linear_shapes(network: nn.Module) -> tuple[tuple[int, int], tuple[int, int]]:
    """``(out, in)`` of the first and last layers of ``network``."""
    if isinstance(network, NoisyQNetwork):
        return tuple(network.layers[0].weight_mu.shape), tuple(network.layers[-1].weight_mu.shape)
    linears = [m for m in network.modules() if isinstance(m, nn.Linear)]
    return tuple(linears[0].weight.shape), tuple(linears[-1].weight.shape)


def _check_dims(path: Path, policy: Policy, state_dim: int | None, n_actions: int | None) -> None:
    if state_dim is not None and policy.state_dim != state_dim:
        raise PolicyError(
            f"{path}: policy expects {policy.state_dim}-dim observations, "
            f"the environment gives {state_dim}"
        )
    if n_actions is not None and policy.n_actions != n_actions:
        raise PolicyError(
            f"{path}: policy has {policy.n_actions} actions, the environment has {n_actions}"
        )


def _sb3_algorithm(data: bytes) -> str | None:
    """``"DQN"``/``"PPO"``/``"other"`` for a Stable-Baselines3 zip, None for any other file.

    The zip's ``data`` entry is JSON of the model's attributes: DQN's policy class lives in
    ``stable_baselines3.dqn.policies``; PPO shares ``ActorCriticPolicy`` with A2C but alone has
    ``clip_range``.
    """
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            if "data" not in archive.namelist() or "policy.pth" not in archive.namelist():
                return None
            meta = json.loads(archive.read("data"))
    except (zipfile.BadZipFile, KeyError, ValueError, OSError):
        return None
    if not isinstance(meta, dict):
        return None
    module = str(meta.get("policy_class", {}).get("__module__", ""))
    if module == "stable_baselines3.dqn.policies" or "target_update_interval" in meta:
        return "DQN"
    if "clip_range" in meta:
        return "PPO"
    return "other"


def _load_sb3(path: Path, algorithm: str) -> Any:
    try:
        import stable_baselines3
    except ImportError:
        raise PolicyError(
            f"{path} is a Stable-Baselines3 {algorithm} model; install stable-baselines3 "
            "(pip install 'oodrl[sb3]') to load it"
        ) from None
    cls = getattr(stable_baselines3, algorithm)
    try:
        return cls.load(path, device="cpu")
    except Exception as exc:  # SB3 can fail in many ways on a damaged zip
        raise PolicyError(
            f"{path}: Stable-Baselines3 could not load it as {algorithm} ({type(exc).__name__}: "
            f"{str(exc).splitlines()[0][:120] if str(exc) else ''})"
        ) from None


def evaluate_policy(
    policy: Policy,
    episodes: int,
    seed: int,
    env_id: str = "LunarLander-v3",
    rngs: Sequence[np.random.Generator] | None = None,
) -> np.ndarray:
    """Undiscounted returns (episodes,) float64 of full episodes seeded seed..seed+episodes-1.

    The episodes run side by side, one environment each, with one batched ``act`` per step.
    In ``noisy`` mode episode ``i`` draws its noise from ``rngs[i]``; by default from
    ``np.random.default_rng(seed + i)``.
    """
    if policy.mode == "noisy" and rngs is None:
        rngs = [np.random.default_rng(seed + i) for i in range(episodes)]
    if rngs is not None and len(rngs) != episodes:
        raise ValueError(f"need one generator per episode ({episodes}); got {len(rngs)}")
    envs = [gym.make(env_id) for _ in range(episodes)]
    try:
        obs = np.stack([env.reset(seed=seed + i)[0] for i, env in enumerate(envs)]).astype(
            np.float32
        )
        returns = np.zeros(episodes)
        active = np.ones(episodes, dtype=bool)
        while active.any():
            rows = np.flatnonzero(active)
            actions = policy.act(obs[rows], None if rngs is None else [rngs[i] for i in rows])
            for i, action in zip(rows, actions, strict=True):
                next_obs, reward, terminated, truncated, _ = envs[i].step(int(action))
                returns[i] += float(reward)
                obs[i] = next_obs
                active[i] = not (terminated or truncated)
    finally:
        for env in envs:
            env.close()
    return returns
