"""Contract checks every detector must pass, for oodrl's own tests and for plugin authors.

    from oodrl.testing import check_detector, linear_system_trajectories

    data = linear_system_trajectories(10, seed=0)
    check_detector(lambda: MyDetector(epochs=2), data[:6], data[6:8], data[8:])
    # and again on continuous actions, (T, 2) float32:
    data = linear_system_trajectories(10, action_dim=2, seed=0)
    check_detector(lambda: MyDetector(epochs=2), data[:6], data[6:8], data[8:])

Each `check_*` function raises AssertionError (or the unexpected oodrl error) on a violation
and can be called on its own; `check_detector` runs them all. A factory, not an instance, is
passed where a check needs fresh detectors: it must return a new, unfitted detector with the
same parameters (and seed) on every call.
"""

from __future__ import annotations

import pickle
import subprocess
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from oodrl.core.detector import BaseDetector, threshold_from_scores
from oodrl.core.trajectory import Trajectory
from oodrl.errors import ContractError, NotFittedError
from oodrl.validation import constraints_of, constructor_params

DetectorFactory = Callable[[], BaseDetector]

#: Tolerance between batched and one-at-a-time scores (batching may change float rounding).
BATCH_RTOL = 1e-5
BATCH_ATOL = 1e-8


def linear_system_trajectories(
    n: int,
    *,
    T: int = 120,  # noqa: N803 - T is the protocol's name for the horizon
    state_dim: int = 4,
    n_actions: int = 3,
    action_dim: int | None = None,
    episode_length: int = 80,
    seed: int = 0,
) -> list[Trajectory]:
    """Cheap deterministic trajectories of a noisy linear system.

    s_{t+1} = A s_t + B(a_t) + 0.1·N(0, I), A a contraction with some rotation. Actions are
    discrete by default: a_t one of `n_actions`, from a noisy linear policy, and B(a) = B[a].
    With `action_dim`, they are continuous, (T, action_dim) float32 in [-1, 1]: a_t = clip(K s_t
    + 0.3·N(0, I)), and B(a) = B a. Episodes last `episode_length` ± 25% steps; as in the
    collector, an episode end sets `dones[t]`, `next_states[t]` is the terminal observation and
    the stream continues from a fresh initial state. The system (A, B, policy) depends on `seed`
    and the action kind only; trajectory i draws from its own generator, so the first k of n
    trajectories do not depend on n.
    """
    dynamics, effects, matrix = _linear_system(seed, state_dim, n_actions, action_dim)
    if action_dim is None:
        act = _discrete_policy(effects, matrix)
    else:
        act = _continuous_policy(effects, matrix)
    return [_trajectory(act, dynamics, T, episode_length, [seed, 1, index]) for index in range(n)]


def linear_system_policy(
    path: str | Path,
    *,
    state_dim: int = 4,
    n_actions: int = 3,
    action_dim: int | None = None,
    seed: int = 0,
) -> Path:
    """Write the policy of `linear_system_trajectories` (same arguments) without its exploration
    noise to `path`, as an oodrl checkpoint, for detectors that read the agent's policy (a
    `policy` parameter); returns the path. Needs torch.

    Discrete: a one-layer `mlp` whose values are P s (the data's actions are argmax(P s + Gumbel
    noise), a softmax policy of those values). Continuous: a one-layer `clipped_actor`,
    clip(K s, −1, 1), a deterministic actor with no value head.
    """
    import torch

    from oodrl.policies.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION

    _, _, matrix = _linear_system(seed, state_dim, n_actions, action_dim)
    if action_dim is None:
        architecture: dict = {"kind": "mlp"}
    else:
        bounds = {"action_low": [-1.0] * action_dim, "action_high": [1.0] * action_dim}
        architecture = {"kind": "clipped_actor", **bounds}
    weights = {
        "net.0.weight": torch.tensor(matrix, dtype=torch.float32),
        "net.0.bias": torch.zeros(len(matrix)),
    }
    checkpoint = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "architecture": architecture,
        "state_dict": weights,
    }
    torch.save(checkpoint, path)
    return Path(path)


def _linear_system(
    seed: int, state_dim: int, n_actions: int, action_dim: int | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The system of `linear_system_trajectories`: the dynamics A, the actions' effects (rows
    B[a] for discrete actions, the matrix B for continuous ones) and the policy's matrix (the
    values' P, or the gain K)."""
    system = np.random.default_rng([seed, 0])
    dynamics = 0.9 * np.linalg.qr(system.standard_normal((state_dim, state_dim)))[0]
    if action_dim is None:
        effects = 0.3 * system.standard_normal((n_actions, state_dim))
        return dynamics, effects, system.standard_normal((n_actions, state_dim))
    effects = 0.3 * system.standard_normal((state_dim, action_dim))
    return dynamics, effects, 0.5 * system.standard_normal((action_dim, state_dim))


#: A policy and the effect of its action: (state, rng) -> (action, its additive effect on s').
ActionModel = Callable[[np.ndarray, np.random.Generator], tuple[np.ndarray, np.ndarray]]


def _discrete_policy(action_effects: np.ndarray, policy: np.ndarray) -> ActionModel:
    n_actions = len(policy)

    def act(state: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        action = np.argmax(policy @ state + rng.gumbel(size=n_actions))
        return action, action_effects[action]

    return act


def _continuous_policy(action_effects: np.ndarray, gain: np.ndarray) -> ActionModel:
    action_dim = len(gain)

    def act(state: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        noisy = gain @ state + 0.3 * rng.standard_normal(action_dim)
        # The stored float32 action is the one that moves the system.
        action = np.clip(noisy, -1.0, 1.0).astype(np.float32)
        return action, action_effects @ action.astype(np.float64)

    return act


def _trajectory(
    act: ActionModel,
    dynamics: np.ndarray,
    T: int,
    episode_length: int,
    seed: list[int],  # noqa: N803
) -> Trajectory:
    rng = np.random.default_rng(seed)
    state_dim = dynamics.shape[0]
    states = np.empty((T, state_dim))
    next_states = np.empty((T, state_dim))
    actions = []
    dones = np.zeros(T, dtype=bool)
    episode_index = np.empty(T, dtype=np.int64)
    episode = 0
    state, remaining = _initial(rng, state_dim, episode_length)
    for t in range(T):
        states[t] = state
        action, effect = act(state, rng)
        actions.append(action)
        next_states[t] = dynamics @ state + effect + 0.1 * rng.standard_normal(state_dim)
        episode_index[t] = episode
        remaining -= 1
        dones[t] = remaining == 0
        if dones[t]:
            state, remaining = _initial(rng, state_dim, episode_length)
            episode += 1
        else:
            state = next_states[t]
    return Trajectory(
        states=states.astype(np.float32),
        actions=np.asarray(actions),
        rewards=-(states**2).sum(axis=1).astype(np.float32),
        next_states=next_states.astype(np.float32),
        dones=dones,
        info={"episode_index": episode_index, "seed": seed[-1]},
    )


def _initial(
    rng: np.random.Generator, state_dim: int, episode_length: int
) -> tuple[np.ndarray, int]:
    """A fresh episode's initial state and its length."""
    length = int(rng.integers(int(0.75 * episode_length), int(1.25 * episode_length) + 1))
    return rng.standard_normal(state_dim), max(length, 1)


def with_extra_state_dimension(trajectory: Trajectory) -> Trajectory:
    """The trajectory with one more (zero) state coordinate: a wrong-dimension input."""
    pad = np.zeros((trajectory.T, 1), dtype=np.float32)
    return trajectory.replace(
        states=np.hstack([trajectory.states, pad]),
        next_states=np.hstack([trajectory.next_states, pad]),
    )


def check_parameters(detector: BaseDetector) -> None:
    """Constraints for every parameter, defaults that validate, a clone."""
    cls = type(detector)
    missing = set(constructor_params(cls)) - set(constraints_of(cls))
    assert not missing, f"{cls.__name__} declares no constraints for {sorted(missing)}."
    detector.validate_params()
    clone = cls.from_params(detector.get_params())
    assert clone.get_params() == detector.get_params(), "from_params(get_params()) differs."


def check_not_fitted(detector: BaseDetector, trajectory: Trajectory) -> None:
    """Scoring or calibrating before `fit` raises NotFittedError."""
    for use in (detector.score, lambda t: detector.calibrate([t])):
        try:
            use(trajectory)
        except NotFittedError:
            continue
        raise AssertionError(f"{detector.name} did not raise NotFittedError before fit.")


def check_scores_use_the_data(
    factory: DetectorFactory,
    fit_trajectories: Sequence[Trajectory],
    trajectories: Sequence[Trajectory],
) -> None:
    """The scores depend on the scored steps and on the fit set.

    Shape, dtype and finiteness are the base class's to enforce; what it cannot see is a
    detector that scores every step alike (an unfinished `_score`) or ignores what it learned
    (stale or unused fitted state). So: the scores vary over the steps, and fitting on the fit
    set moved and stretched changes them (unless the detector declares `learns_from_data =
    False`: a baseline that ignores the fit set by design).
    """
    detector = factory()
    scores = [o.scores for o in detector.fit(fit_trajectories).score_many(trajectories)]
    steps = np.concatenate(scores)
    assert np.ptp(steps) > 0, f"every step scored {steps[0]}: the scores ignore the steps."
    if not detector.learns_from_data:
        return
    moved = [_moved_and_stretched(t) for t in fit_trajectories]
    refitted = [o.scores for o in factory().fit(moved).score_many(trajectories)]
    assert any(not np.array_equal(a, b) for a, b in zip(scores, refitted, strict=True)), (
        "fitting on other data gave the same scores: the scores ignore the fit set."
    )


def _moved_and_stretched(trajectory: Trajectory) -> Trajectory:
    """The trajectory with every observation x replaced by 3x + 1."""
    return trajectory.replace(
        states=3 * trajectory.states + 1, next_states=3 * trajectory.next_states + 1
    )


def check_reproducible(
    factory: DetectorFactory,
    fit_trajectories: Sequence[Trajectory],
    trajectories: Sequence[Trajectory],
) -> None:
    """Two fits with the same parameters and seed give identical scores and pickle bytes
    (the pipeline's fit outputs must reproduce bit for bit)."""
    one, two = factory().fit(fit_trajectories), factory().fit(fit_trajectories)
    assert pickle.dumps(one) == pickle.dumps(two), (
        f"{one.name}: two fits pickle to different bytes (fitted state that is not "
        "byte-reproducible, e.g. a scipy cKDTree, must be rebuilt when scoring)."
    )
    first, second = one.score_many(trajectories), two.score_many(trajectories)
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a.scores, b.scores, err_msg="refit changed the scores")


def check_score_is_pure(detector: BaseDetector, trajectories: Sequence[Trajectory]) -> None:
    """Scoring leaves the detector unchanged (same pickle) and gives the same scores twice."""
    before = pickle.dumps(detector)
    first = [o.scores for o in detector.score_many(trajectories)]
    second = [detector.score(t).scores for t in trajectories]
    assert pickle.dumps(detector) == before, f"{detector.name}.score changed the detector."
    for one, batched in zip(second, first, strict=True):
        np.testing.assert_allclose(
            one,
            batched,
            rtol=BATCH_RTOL,
            atol=BATCH_ATOL,
            err_msg="score(t) differs from score_many([..., t, ...])",
        )
    repeat = [o.scores for o in detector.score_many(trajectories)]
    for a, b in zip(first, repeat, strict=True):
        np.testing.assert_array_equal(a, b, err_msg="scoring twice gave different scores")


def check_state_dim(detector: BaseDetector, trajectory: Trajectory) -> None:
    """A trajectory of another state dimension than the fit one raises ContractError."""
    try:
        detector.score(with_extra_state_dimension(trajectory))
    except ContractError:
        return
    raise AssertionError(f"{detector.name} scored a wrong-dimension trajectory.")


def check_threshold(detector: BaseDetector, calibration: Sequence[Trajectory]) -> None:
    """`calibrate` sets the declared rule's threshold of the calibration scores; alarms follow."""
    scores = [o.scores for o in detector.score_many(calibration)]
    detector.calibrate(calibration)
    expected = threshold_from_scores(
        scores, detector.threshold_rule, detector.threshold_percentile, detector.alpha
    )
    assert detector.threshold_ == expected, f"threshold {detector.threshold_} != {expected}"
    output = detector.score(calibration[0])
    assert output.threshold == expected
    np.testing.assert_array_equal(output.alarms, output.scores >= expected)


def check_streaming(detector: BaseDetector, trajectories: Sequence[Trajectory]) -> None:
    """`detector.stream()` fed the steps of each trajectory and flushed returns every step's
    score once, in step order, equal bit for bit to `score`, with the same alarms. One stream
    object serves all the trajectories in turn (`flush` starts a new stream)."""
    stream = detector.stream()
    for index, trajectory in enumerate(trajectories):
        records = []
        for t in range(trajectory.T):
            records.extend(
                stream.update(
                    trajectory.states[t],
                    trajectory.actions[t],
                    trajectory.rewards[t],
                    trajectory.next_states[t],
                    trajectory.dones[t],
                )
            )
        records.extend(stream.flush())
        steps = [r.step for r in records]
        assert steps == list(range(trajectory.T)), (
            f"{detector.name}: trajectory {index} streamed steps {steps[:5]}…; expected each "
            f"of 0..{trajectory.T - 1} once, in order."
        )
        streamed = np.array([r.score for r in records])
        batch = detector.score(trajectory)
        differ = np.flatnonzero(streamed.view(np.int64) != batch.scores.view(np.int64))
        assert differ.size == 0, (
            f"{detector.name}: trajectory {index} streamed {differ.size} scores that differ "
            f"from score(), first at step {differ[:1]}: {streamed[differ[:1]]} vs "
            f"{batch.scores[differ[:1]]}."
        )
        alarms = batch.alarms if batch.alarms is not None else np.zeros(trajectory.T, bool)
        np.testing.assert_array_equal([r.alarm for r in records], alarms)


def check_pickle_roundtrip(detector: BaseDetector, trajectories: Sequence[Trajectory]) -> None:
    """A pickled and reloaded detector scores exactly like the original."""
    clone = pickle.loads(pickle.dumps(detector))
    for a, b in zip(detector.score_many(trajectories), clone.score_many(trajectories), strict=True):
        np.testing.assert_array_equal(a.scores, b.scores, err_msg="unpickled detector differs")


def check_global_random_state(
    factory: DetectorFactory,
    fit_trajectories: Sequence[Trajectory],
    trajectories: Sequence[Trajectory],
) -> None:
    """Fitting and scoring leave numpy's and (if loaded) torch's global random state untouched."""
    # The legacy global state is exactly what must stay untouched, hence NPY002.
    numpy_before = pickle.dumps(np.random.get_state())  # noqa: NPY002
    torch = sys.modules.get("torch")
    torch_before = torch.get_rng_state() if torch is not None else None
    factory().fit(fit_trajectories).score_many(trajectories)
    numpy_after = pickle.dumps(np.random.get_state())  # noqa: NPY002
    assert numpy_after == numpy_before, "numpy's global RNG was used."
    if torch is not None:
        assert torch.equal(torch.get_rng_state(), torch_before), "torch's global RNG was used."


def check_torch_free_import(detector: BaseDetector) -> None:
    """Importing, building and validating the detector does not import torch (fresh process).

    Every pipeline stage builds every configured detector when it validates the params, so a
    detector that needs torch imports it only where it fits or scores (`uses_torch` says so).
    """
    code = (
        "import pickle, sys; detector = pickle.load(sys.stdin.buffer); "
        "type(detector).from_params(detector.get_params()).validate_params(); "
        "sys.exit('torch' in sys.modules)"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], input=pickle.dumps(detector), capture_output=True
    )
    assert result.returncode == 0, (
        f"building {detector.name} imported torch. {result.stderr.decode()}"
    )


def check_detector(
    factory: DetectorFactory,
    fit_trajectories: Sequence[Trajectory],
    calibration_trajectories: Sequence[Trajectory],
    eval_trajectories: Sequence[Trajectory],
) -> None:
    """Run every contract check on one detector configuration."""
    fresh = factory()
    check_parameters(fresh)
    check_torch_free_import(fresh)
    check_not_fitted(fresh, eval_trajectories[0])
    fitted = factory()
    assert fitted.fit(fit_trajectories) is fitted, "fit must return the detector itself"
    check_scores_use_the_data(factory, fit_trajectories, eval_trajectories)
    check_reproducible(factory, fit_trajectories, eval_trajectories)
    check_global_random_state(factory, fit_trajectories, eval_trajectories)
    check_score_is_pure(fitted, eval_trajectories)
    check_state_dim(fitted, eval_trajectories[0])
    check_threshold(fitted, calibration_trajectories)
    check_streaming(fitted, eval_trajectories)
    check_pickle_roundtrip(fitted, eval_trajectories)
