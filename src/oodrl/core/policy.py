"""The Policy protocol collectors act with."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np


class Policy(Protocol):
    """Maps a batch of observations (n, d) to actions (n,).

    `rngs[i]` is the noise stream of row i's deployment stream (NoisyNet noise in `noisy`
    mode); a deterministic policy ignores it. Rows must not influence each other.
    """

    state_dim: int
    n_actions: int
    sha256: str

    def act(
        self, observations: np.ndarray, rngs: Sequence[np.random.Generator] | None
    ) -> np.ndarray: ...
