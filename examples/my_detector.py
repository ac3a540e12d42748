"""A detector of your own, as a plugin module would hold it (imported by
examples/evaluate_detector.py).

Its score is how far a step's state lies from the clean fit steps, coordinate by coordinate:
the largest absolute z-score of s_t. It reads step t alone (`row_independent`), so its stream
scores each step on its own, in constant work.
"""

from __future__ import annotations

import numpy as np

import oodrl


class MaxAbsZScore(oodrl.BaseDetector):
    """max_i |s_t,i − μ_i| / σ_i over the state's coordinates (μ, σ from the fit steps)."""

    row_independent = True

    def _fit(self, trajectories):
        states = np.concatenate([t.states for t in trajectories])
        self.mean_ = states.mean(axis=0)
        self.scale_ = states.std(axis=0) + 1e-9

    def _score(self, trajectory):
        return np.max(np.abs(trajectory.states - self.mean_) / self.scale_, axis=1)
