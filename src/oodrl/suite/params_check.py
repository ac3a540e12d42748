"""What `oodrl check-params` checks beyond each section's ranges and each component's declared
constraints (`oodrl.config`), so that nothing that passes it fails later for a params reason
(SPEC §22). Only check-params (and `oodrl new`) runs these; no stage pays for them.

- `check_protocol`: the protocol's seed ranges never overlap (ID, evaluation, tier calibration
  and impact streams each have seeds of their own), the tier search's sizes fit its seed blocks
  and its budget (`TierSearchConfig.check_seed_blocks`), a detector whose threshold rule is
  `episode_max` has the held-out streams its `alpha` needs, and no library detector's block
  sets a key of oodrl's that oodrl would ignore and the library would have read.
- `check_library_detectors`: every library detector (SPEC §17) is fitted and scored on dummy
  data shaped like its fit set (the environment's state and action sizes), because a library
  checks some arguments only in fit: PyOD's KNN hands `n_neighbors` to scikit-learn there, PyOD's
  LOF finds it cannot score without novelty there, HBOS checks `n_bins` there.
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Callable, Sequence
from fractions import Fraction
from typing import TYPE_CHECKING, Any

import numpy as np

from oodrl.errors import ConfigError

if TYPE_CHECKING:
    from oodrl.config import Params
    from oodrl.core.adapter import EnvironmentAdapter
    from oodrl.core.detector import BaseDetector
    from oodrl.core.trajectory import Trajectory
    from oodrl.detectors.library import LibraryDetector

#: The dummy fit set tried first: a few short streams, so that probing costs milliseconds. Only
#: when a detector fails on it is it tried on the fit set's full size (`_fits`).
SMALL_STREAMS, SMALL_T = 2, 16


def check_completely(params: Params) -> None:
    """Everything `oodrl check-params` checks beyond loading (SPEC §22: nothing that passes it
    fails later for a params reason); it makes the environment, so no stage pays for this."""
    from oodrl.envs import ENVIRONMENTS

    detectors = {name: params.detector(name) for name in params.detectors}
    _check_seed_ranges(params)
    _check_calibration_counts(params, detectors)
    _check_conditional_calibration(params)
    _check_shadowed_keys(params, detectors)
    adapter = ENVIRONMENTS.get(params.env.id)()
    for name in params.anomaly.injectors:
        try:
            params.injector(name).check_adapter(adapter)
        except ConfigError as error:
            raise ConfigError(f"anomaly.injectors.{name}: {error}") from None
    check_library_detectors(params, adapter)


def _check_seed_ranges(params: Params) -> None:
    """Each set of streams on seeds of its own (offsets from `seed`): an overlap would replay
    one set's episodes as another's (an evaluation stream fitted on, a calibration stream
    that is an evaluation stream's twin)."""
    from oodrl.config import (
        CRN_SEARCH_SEED_OFFSET,
        CRN_VERIFY_SEED_OFFSET,
        POLICY_SEED_OFFSET,
        RANDOM_SEED_OFFSET,
    )
    from oodrl.protocol.impact import LEVELS

    data, tiers, search = params.data, params.tiers, params.tiers.search
    # The tier search's blocks fit (their sizes, its budget), before any overlap is looked at.
    search.check_seed_blocks(len(LEVELS))
    verify = search.max_verify_batches * search.verify_batch  # numbered over the fault
    # (the key to change when the range overlaps an earlier one, its streams, first seed, count)
    sets = [
        ("data.n_id", "ID streams", 0, data.n_id),
        ("tiers.episodes", "policy's impact episodes", POLICY_SEED_OFFSET, tiers.episodes),
        ("tiers.episodes", "random policy's impact episodes", RANDOM_SEED_OFFSET, tiers.episodes),
        ("tiers.search.search_episodes", "tier search's episodes", CRN_SEARCH_SEED_OFFSET,
         search.search_episodes),
        ("tiers.search.verify_batch", "tier verification's episodes", CRN_VERIFY_SEED_OFFSET,
         verify),
        ("data.eval_seed_offset", "evaluation streams and the tier cells' twins",
         data.eval_seed_offset, max(data.n_ood, tiers.n_streams)),
        ("tiers.calibration_seed_offset", "tier calibration streams",
         tiers.calibration_seed_offset, tiers.n_calibration),
        ("tiers.audit_seed_offset", "audit streams", tiers.audit_seed_offset, tiers.n_audit),
    ]  # fmt: skip
    ranges = [(key, what, range(first, first + count)) for key, what, first, count in sets]
    for i, (key, what, seeds) in enumerate(ranges):
        for _, other, earlier in ranges[:i]:
            if seeds.start < earlier.stop and earlier.start < seeds.stop:
                raise ConfigError(
                    f"{key}: the {what} (seeds seed + {_shown(seeds)}) overlap the {other} "
                    f"(seed + {_shown(earlier)}). Allowed: values that keep every set of "
                    "streams on seeds of its own."
                )


def _check_conditional_calibration(params: Params) -> None:
    """The training-conditional rule at (alpha, delta) needs n with (1 - alpha)^n <= delta
    (SPEC §19); here, not on load, so that no stage's code stamp holds the metrics' code."""
    from oodrl.metrics.operating import conditional_shortfall

    tiers = params.tiers
    if tiers.threshold_rule == "episode_max_conditional":
        shortfall = conditional_shortfall(tiers.n_calibration, tiers.alpha, tiers.delta)
        if shortfall:
            raise ConfigError(f"tiers.n_calibration: {shortfall}")


def _shown(seeds: range) -> str:
    return f"{seeds.start}..{seeds.stop - 1}"


def _check_calibration_counts(params: Params, detectors: dict[str, BaseDetector]) -> None:
    """`episode_max` calibrates on the ID set's held-out streams (the fit stage): at alpha it
    needs ceil(1/alpha) - 1 of them, or the fit stage refuses after collection ran."""
    n = params.data.n_calibration
    for name, detector in detectors.items():
        if detector.threshold_rule != "episode_max":
            continue
        alpha = detector.alpha
        needed = math.ceil(1 / Fraction(str(alpha))) - 1
        if n < needed:
            raise ConfigError(
                f"detectors.{name}.alpha: threshold_rule episode_max at alpha={alpha} needs at "
                f"least {needed} held-out streams (ceil(1/alpha) - 1); data.n_id = "
                f"{params.data.n_id} and data.calibration_fraction = "
                f"{params.data.calibration_fraction} hold out {n}. Allowed: alpha >= 1/{n + 1} "
                f"({math.ceil(10_000 / (n + 1)) / 10_000} or more), or more held-out streams."
            )


def _check_shadowed_keys(params: Params, detectors: dict[str, BaseDetector]) -> None:
    """A key of oodrl's that the library class takes too and oodrl would not read (HBOS's
    `alpha` under the percentile rule): the value was meant for the library, which never
    gets it."""
    from oodrl.detectors.library import LibraryDetector
    from oodrl.validation import ParameterError

    for name, detector in detectors.items():
        if isinstance(detector, LibraryDetector):
            try:
                detector.refuse_shadowed(params.detectors[name])
            except ParameterError as error:
                raise ConfigError(f"detectors.{name}.{error.param}: {error}") from None


def check_library_detectors(params: Params, adapter: EnvironmentAdapter) -> None:
    """Fit and score every library detector on dummy streams of the environment's sizes; a
    failure is one ConfigError naming `detectors.<name>.<key>` where one key alone fails, else
    `detectors.<name>`."""
    from oodrl.detectors.library import LibraryDetector

    small = _streams(adapter, SMALL_STREAMS, min(SMALL_T, params.env.T))
    n_fit = params.data.n_id - params.data.n_calibration
    full = functools.cache(lambda: _streams(adapter, n_fit, params.env.T))
    for name, block in params.detectors.items():
        detector = params.detector(name)
        if not isinstance(detector, LibraryDetector):
            continue
        try:
            _fits(detector, small, full)
        except Exception as error:  # the library's own error, whatever its type
            raise _named(error, name, block, detector, small, full) from None


def _named(
    error: Exception,
    name: str,
    block: dict[str, Any],
    detector: LibraryDetector,
    small: Sequence[Trajectory],
    full: Callable[[], list[Trajectory]],
) -> ConfigError:
    """The probe's error as one line naming the detector's params key and, where one library
    argument alone makes it fail, that argument's."""
    from oodrl.detectors.library import blame, one_line

    own = {k: v for k, v in block.items() if k not in detector.library_params}
    key = blame(
        detector.library_params,
        lambda one: _fits(type(detector).from_params({**own, **one}), small, full),
    )
    message = one_line(error)
    if not message.startswith(detector.name):
        message = f"{detector.name}: {message}"
    return ConfigError(f"detectors.{name}{f'.{key}' if key else ''}: {message}")


def _fits(
    detector: LibraryDetector, small: Sequence[Trajectory], full: Callable[[], list[Trajectory]]
) -> None:
    """Fit and score on the small set; a failure counts only when the full-size set fails too
    (a kNN's n_neighbors = 50 is fine on 12,000 fit rows, not on 32)."""
    from oodrl.detectors.library import cache_numba_kernels

    # numba's on-disk cache: HBOS compiles for seconds otherwise. Safe here, unlike in the fit
    # stage, since nothing fitted here is pickled (`oodrl.detectors.library`).
    cache_numba_kernels(detector.library_class.__module__)
    with warnings.catch_warnings():
        # A library's warnings on dummy data (n_neighbors clipped to the rows) are no error.
        warnings.simplefilter("ignore")
        try:
            detector.fit(small).score(small[0])
        except Exception:
            streams = full()
            detector.fit(streams).score(streams[0])


def _streams(adapter: EnvironmentAdapter, n: int, T: int) -> list[Trajectory]:  # noqa: N803
    """`n` standard-normal streams of T steps with the environment's state and action sizes;
    every discrete action occurs, so the one-hot views are as wide as the real ones."""
    from oodrl.core.trajectory import Trajectory

    rng = np.random.default_rng(0)
    d = adapter.state_dim
    streams = []
    for i in range(n):
        states = rng.standard_normal((T, d))
        if adapter.action_kind == "discrete":
            actions = np.arange(i * T, (i + 1) * T) % adapter.action_size
        else:
            actions = rng.standard_normal((T, adapter.action_size))
        next_states = states + 0.1 * rng.standard_normal((T, d))
        streams.append(Trajectory(states, actions, np.zeros(T), next_states, np.zeros(T, bool)))
    return streams
