"""Streaming scores equal batch scores bit for bit, for every registered detector (ids = name),
on discrete and continuous actions, across `done` resets inside the stream (SPEC §13)."""

from __future__ import annotations

import numpy as np
import pytest
from test_contract import NAMES, SPLITS, by_name_and_actions, fitted

from oodrl.core.detector import BaseDetector
from oodrl.core.stream import ReplayStream, RowStream
from oodrl.detectors import DETECTORS
from oodrl.testing import check_streaming, linear_system_trajectories


def test_the_evaluation_streams_cross_episode_resets():
    for _, calibration, evaluation in SPLITS.values():
        assert all(t.dones[:-1].any() for t in [*calibration, *evaluation])


@by_name_and_actions
def test_streaming_equals_batch_scores(name, actions):
    detector = fitted(name, actions)
    _, calibration, evaluation = SPLITS[actions]
    detector.calibrate(calibration)
    check_streaming(detector, evaluation)


@pytest.mark.parametrize("name", NAMES, ids=NAMES)
def test_every_detector_streams_in_constant_work(name):
    stream = fitted(name, "discrete").stream()
    assert not isinstance(stream, ReplayStream), f"{name} streams by re-scoring the past."


VARIANTS = {
    "cusum_state_reset_on_done": ("cusum", {"residual": "state", "reset_on_done": True}),
    "mahalanobis_transition": ("mahalanobis_distance", {"features": "transition"}),
    "kde_state_action": ("kde_density", {"features": "state_action", "max_reference": 100}),
    "lyapunov_lag2_dim3": (
        "lyapunov_divergence",
        {"embedding_dim": 3, "lag": 2, "horizon": 3, "max_reference": 200},
    ),
    "time_series_robust_z": ("time_series_features", {"window": 8, "distance": "robust_z"}),
}


@pytest.mark.parametrize("variant", list(VARIANTS), ids=list(VARIANTS))
def test_streaming_equals_batch_for_other_parameters(variant):
    name, params = VARIANTS[variant]
    fit, _, evaluation = SPLITS["continuous"]
    check_streaming(DETECTORS.get(name)(**params).fit(fit), evaluation)


def test_episode_ending_on_the_last_step_and_short_episodes():
    # Episodes of 3 to 5 steps: lyapunov's horizon 5 never runs in full; the last step is a done.
    data = linear_system_trajectories(4, T=40, episode_length=4, seed=3)
    ended = data[3].replace(dones=np.r_[data[3].dones[:-1], True])
    detector = DETECTORS.get("lyapunov_divergence")(horizon=2, max_reference=50).fit(data[:3])
    check_streaming(detector, [ended, data[3]])


class _PrefixMean(BaseDetector):
    """A plugin scoring only whole trajectories: the running mean of the first coordinate."""

    def _fit(self, trajectories):
        self.offset_ = float(np.mean([t.states[:, 0].mean() for t in trajectories]))

    def _score(self, trajectory):
        x = trajectory.states[:, 0].astype(np.float64) - self.offset_
        return np.cumsum(x) / np.arange(1, trajectory.T + 1)


class _LooksAhead(_PrefixMean):
    """Declares latency 2 and reads two steps ahead."""

    @property
    def latency(self):
        return 2

    def _score(self, trajectory):
        x = np.abs(trajectory.states[:, 0].astype(np.float64) - self.offset_)
        return np.convolve(np.r_[x, 0.0, 0.0], np.ones(3), mode="valid")


class _Undeclared(_LooksAhead):
    """Reads two steps ahead but declares no latency: its default stream cannot be exact."""

    @property
    def latency(self):
        return 0


@pytest.mark.parametrize("plugin", [_PrefixMean, _LooksAhead], ids=["causal", "look_ahead"])
def test_default_stream_of_a_batch_only_plugin_is_exact(plugin):
    fit, calibration, evaluation = SPLITS["discrete"]
    detector = plugin().fit(fit).calibrate(calibration)
    assert isinstance(detector.stream(), ReplayStream)
    check_streaming(detector, evaluation)


def test_the_contract_catches_an_undeclared_look_ahead():
    fit, _, evaluation = SPLITS["discrete"]
    with pytest.raises(AssertionError, match="differ from score"):
        check_streaming(_Undeclared().fit(fit), evaluation)


def test_row_independent_detectors_score_each_step_alone():
    assert isinstance(fitted("mahalanobis_distance", "discrete").stream(), RowStream)


def test_first_scores_and_alarms_as_steps_arrive():
    fit, calibration, evaluation = SPLITS["discrete"]
    detector = DETECTORS.get("lyapunov_divergence")(horizon=3, max_reference=200).fit(fit)
    detector.calibrate(calibration)
    trajectory = evaluation[0]
    stream = detector.stream()
    arrived = []
    for t in range(6):
        step = (trajectory.states[t], trajectory.actions[t], 0.0, trajectory.next_states[t], False)
        arrived.append([r.step for r in stream.update(*step)])
    # z_t needs s_{t+3}: it comes with the update of step t + 3.
    assert arrived == [[], [], [], [0], [1], [2]]
