"""The Policy protocol collectors act with."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal, Protocol

import numpy as np

#: How a policy acts: an index into a finite set, or a real vector.
ActionKind = Literal["discrete", "continuous"]


class Policy(Protocol):
    """Maps a batch of observations (n, state_dim) to actions: (n,) int64 indices for
    discrete actions, (n, action_size) float32 vectors for continuous ones.

    `rngs[i]` is the noise stream of row i's deployment stream (NoisyNet noise in `noisy`
    mode); a deterministic policy ignores it. Rows must not influence each other.
    """

    state_dim: int
    action_kind: ActionKind
    #: The number of discrete actions, or the continuous action vector's dimension.
    action_size: int
    sha256: str
    mode: str

    def act(
        self, observations: np.ndarray, rngs: Sequence[np.random.Generator] | None
    ) -> np.ndarray: ...
