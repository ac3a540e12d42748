"""A fault wrapper that records what happens around each of the steps it acts on."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from oodrl.core.injector import Fault


class Step(NamedTuple):
    """One step: the simulator's state before it, its own state after it (before the fault
    writes), the commanded action, the state after the fault, and the observation returned."""

    t: int
    before: np.ndarray
    own: np.ndarray
    commanded: np.ndarray
    written: np.ndarray
    returned: np.ndarray


class Recording(Fault):
    """Wraps a fault and records a `Step` per step it is called on."""

    def __init__(self, inner: Fault) -> None:
        self.inner = inner
        self.calls: list[Step] = []
        self._before: np.ndarray | None = None

    def before_step(self, t, commanded, sim):
        self._before = sim.read_state()
        return self.inner.before_step(t, commanded, sim)

    def after_step(self, t, observation, commanded, sim):
        own = sim.read_state()
        returned = self.inner.after_step(t, observation, commanded, sim)
        step = Step(t, self._before, own, np.array(commanded), sim.read_state(), np.array(returned))
        self.calls.append(step)
        return returned
