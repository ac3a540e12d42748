"""Read a policy file, whatever its format (the formats are told apart by content, not name).

Accepted files:

- an oodrl checkpoint (:mod:`oodrl.policies.checkpoint`) — ``{"format": "oodrl-policy",
  "version": 1, "architecture": {...}, "state_dict": {...}, ...}``;
- a plain torch ``state_dict`` (or ``{"state_dict": ...}``) with an ``architecture`` argument
  naming the network: ``{"kind": "mlp"}`` (Linear/ReLU, acted on by argmax),
  ``{"kind": "noisy_dqn"}``, or ``{"kind": "tanh_actor", "action_low": [...],
  "action_high": [...]}``;
- a callable's pointer (``oodrl new --policy module:function``, SPEC §18): JSON
  ``{"format": "oodrl-callable", "callable": "pkg.module:act", "state_dim": ...,
  "action_kind": ..., "action_size": ...}``; ``act(observations (n, d) float32)`` returns the
  actions. oodrl cannot certify such code machine-independent (``certified`` is False);
- a Stable-Baselines3 ``.zip`` (A2C, DQN, PPO, SAC or TD3), loaded by SB3's own loader on CPU
  and acted on deterministically. stable-baselines3 is an optional dependency (``oodrl[sb3]``);
  its actions come from torch kernels, so they are not machine-independent: convert it to an
  oodrl checkpoint (`oodrl.policies.convert`, `oodrl new`) for a reproducible benchmark.

oodrl checkpoints and state_dicts act through :mod:`oodrl.policies.act` (numpy, machine-independent
arithmetic). Every torch load uses ``weights_only=True``. A missing, corrupt or foreign file raises
:class:`oodrl.errors.PolicyError` with a one-line message.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from oodrl.errors import PolicyError
from oodrl.policies.act import ARCHITECTURE_KINDS, PolicyMode, policy_from_checkpoint
from oodrl.policies.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION

SB3_ALGORITHMS = ("A2C", "DQN", "PPO", "SAC", "TD3")
ACCEPTED = (
    "accepted: an oodrl checkpoint (models/policy.pt), a torch state_dict with "
    f"architecture={{'kind': one of {list(ARCHITECTURE_KINDS)}, ...}}, "
    f"or a Stable-Baselines3 {'/'.join(SB3_ALGORITHMS)} .zip"
)


CALLABLE_FORMAT = "oodrl-callable"


class CallablePolicy:
    """A user's ``module:function`` acting on a batch of observations (not certified
    machine-independent). The function is looked up on every call, so the policy pickles to
    collection's worker processes as its import path alone."""

    mode = "greedy"
    kind = "callable"
    certified = False

    def __init__(self, spec: Mapping[str, Any], sha256: str) -> None:
        self.path = str(spec["callable"])
        self.state_dim = int(spec["state_dim"])
        self.action_kind = str(spec["action_kind"])
        self.action_size = int(spec["action_size"])
        self.sha256 = sha256

    def act(self, obs: np.ndarray, rngs: Sequence[np.random.Generator] | None = None) -> np.ndarray:
        from oodrl.registry import import_path

        obs = np.asarray(obs, dtype=np.float32).reshape(-1, self.state_dim)
        actions = np.asarray(import_path(self.path)(obs))
        if self.action_kind == "discrete":
            return actions.astype(np.int64).reshape(-1)
        return actions.astype(np.float32).reshape(-1, self.action_size)


def callable_spec(data: bytes) -> dict[str, Any] | None:
    """The pointer of a callable policy, or None for any other file."""
    if not data.startswith(b"{"):
        return None
    try:
        spec = json.loads(data)
    except ValueError:
        return None
    return spec if isinstance(spec, dict) and spec.get("format") == CALLABLE_FORMAT else None


class Sb3Policy:
    """A Stable-Baselines3 model acting deterministically (``predict(deterministic=True)``)."""

    mode = "greedy"

    def __init__(self, model: Any, *, kind: str, sha256: str) -> None:
        import gymnasium as gym

        self.model = model
        self.kind = kind
        self.sha256 = sha256
        self.state_dim = int(np.prod(model.observation_space.shape))
        space = model.action_space
        if isinstance(space, gym.spaces.Discrete):
            self.action_kind, self.action_size = "discrete", int(space.n)
        elif isinstance(space, gym.spaces.Box):
            self.action_kind, self.action_size = "continuous", int(np.prod(space.shape))
        else:
            raise PolicyError(f"{kind} model has action space {space}; need Discrete or Box")

    def act(self, obs: np.ndarray, rngs: Sequence[np.random.Generator] | None = None) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float32).reshape(-1, self.state_dim)
        actions, _ = self.model.predict(obs, deterministic=True)
        if self.action_kind == "discrete":
            return np.asarray(actions, dtype=np.int64).reshape(-1)
        return np.asarray(actions, dtype=np.float32).reshape(-1, self.action_size)


def load_policy(
    path: str | Path,
    mode: PolicyMode = "greedy",
    architecture: Mapping[str, Any] | None = None,
    state_dim: int | None = None,
    action_size: int | None = None,
):
    """Load the policy stored at ``path`` (see the module docstring for the accepted files).

    ``architecture`` is needed only for a plain state_dict. ``state_dim`` and ``action_size``
    (number of discrete actions, or the continuous action dimension) are checked when given.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise PolicyError(f"cannot read policy file {path}: {exc.strerror or exc}") from None
    if mode not in ("greedy", "noisy"):
        raise PolicyError(f"policy mode must be 'greedy' or 'noisy'; got {mode!r}")
    sha256 = hashlib.sha256(data).hexdigest()
    spec = callable_spec(data)
    if spec is not None:
        policy = CallablePolicy(spec, sha256)
        _check_dims(path, policy, state_dim, action_size)
        return policy
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
        policy: Any = Sb3Policy(
            _load_sb3(path, sb3_algorithm), kind=f"sb3_{sb3_algorithm.lower()}", sha256=sha256
        )
    else:
        architecture, state_dict = _read_torch(path, data, architecture)
        try:
            policy = policy_from_checkpoint(architecture, state_dict, mode, sha256)
        except PolicyError as error:
            raise PolicyError(f"{path}: {error}") from None
    _check_dims(path, policy, state_dim, action_size)
    return policy


def _read_torch(
    path: Path, data: bytes, architecture: Mapping[str, Any] | None
) -> tuple[Mapping[str, Any], Mapping[str, Any]]:
    """``(architecture, state_dict)`` of a torch file: an oodrl checkpoint or a state_dict."""
    import torch

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
        return obj["architecture"], obj["state_dict"]
    if isinstance(obj, Mapping) and architecture is not None:
        return architecture, _strip_common_prefix(obj.get("state_dict", obj))
    if isinstance(obj, Mapping):
        raise PolicyError(
            f"{path} holds a plain state_dict; pass architecture={{'kind': one of "
            f"{list(ARCHITECTURE_KINDS)}, ...}} to load it"
        )
    raise PolicyError(f"{path} holds a {type(obj).__name__}, not a policy; {ACCEPTED}")


def _strip_common_prefix(state_dict: Mapping[str, Any]) -> dict[str, Any]:
    """Drop a prefix shared by every key (``net.``, ``q_net.``, ``module.``) from a state_dict."""
    keys = list(state_dict)
    for prefix in ("module.", "q_net.", "net.", "model."):
        if keys and all(k.startswith(prefix) for k in keys):
            return _strip_common_prefix({k[len(prefix) :]: v for k, v in state_dict.items()})
    return dict(state_dict)


def _check_dims(path: Path, policy: Any, state_dim: int | None, action_size: int | None) -> None:
    if state_dim is not None and policy.state_dim != state_dim:
        raise PolicyError(
            f"{path}: policy expects {policy.state_dim}-dim observations, "
            f"the environment gives {state_dim}"
        )
    if action_size is not None and policy.action_size != action_size:
        raise PolicyError(
            f"{path}: policy has {policy.action_size} actions (or action dimensions), "
            f"the environment has {action_size}"
        )


def _sb3_algorithm(data: bytes) -> str | None:
    """``"A2C"``/``"DQN"``/``"PPO"``/``"SAC"``/``"TD3"``/``"other"`` for an SB3 zip, None for
    other files.

    The zip's ``data`` entry is JSON of the model's attributes; the policy class's module names
    the algorithm (PPO shares ``ActorCriticPolicy`` with A2C but alone has ``clip_range``).
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
    for algorithm in ("dqn", "sac", "td3"):
        if module == f"stable_baselines3.{algorithm}.policies":
            return algorithm.upper()
    if "target_update_interval" in meta:
        return "DQN"
    if "clip_range" in meta:
        return "PPO"
    if module == "stable_baselines3.common.policies":
        return "A2C"
    return "other"


def quiet_sb3_logger() -> Any:
    """A Stable-Baselines3 logger that writes nothing anywhere. An SB3 model trained with
    verbose=0 otherwise makes a logger whose folder, an empty `SB3-<date>` in the system's
    temporary directory, is left behind by every training."""
    from stable_baselines3.common.logger import Logger

    return Logger(folder=None, output_formats=[])


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
