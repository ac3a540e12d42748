"""The metrics stage's API: per-episode metrics of SPEC §6 and their bootstrap summaries.

`episode_metrics` evaluates every registered metric (built-ins and plugins) on N paired
episodes — perturbed scores z̃ and the matched clean scores z of the same evaluation episode —
and `null_episode_metrics` evaluates the null baseline on the clean scores alone.
`summarise` turns the per-episode values into YAML-safe {mean, std, ci_low, ci_high,
n_episodes} with the seeded episode bootstrap.

A metric is a `Metric`: `compute(batch, settings) -> (N,)` values, one per episode, and
whether a higher value is better. Plugins register one under the `oodrl.metrics` entry-point
group (or as a `module:OBJECT` path) and are then computed for every anomaly record.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from oodrl.errors import ContractError, DetectorError
from oodrl.metrics import METRICS
from oodrl.metrics.alarms import (
    alarm_rate,
    detection_delay,
    precision_recall_f1,
    segment_precision_recall,
)
from oodrl.metrics.bootstrap import episode_bootstrap, paired_bootstrap
from oodrl.metrics.ranking import (
    auroc_rows,
    average_precision_rows,
    fpr_at_tpr_rows,
    temporal_auroc_rows,
    vus_pr_rows,
)

if TYPE_CHECKING:
    from oodrl.config import MetricsConfig


@dataclass(frozen=True, eq=False)
class EpisodeBatch:
    """N paired episodes: perturbed and matched clean scores (N, T), labels (N, T) bool,
    the detector's alarm threshold θ, the anomaly window [onset, offset), and the detector's
    latency (a score of step t is known at t + latency; see `BaseDetector.latency`)."""

    perturbed: np.ndarray
    clean: np.ndarray
    labels: np.ndarray
    threshold: float
    onset: int
    offset: int | None = None
    latency: int = 0

    @property
    def alarms(self) -> np.ndarray:
        """Alarms on the perturbed scores, z̃ ≥ θ."""
        return self.perturbed >= self.threshold

    @property
    def clean_alarms(self) -> np.ndarray:
        """Alarms on the clean scores, z ≥ θ."""
        return self.clean >= self.threshold

    def matched(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Scores [z̃ | z] with positives z̃[P] and negatives z[P] for the matched metrics."""
        nothing = np.zeros_like(self.labels)
        return (
            np.concatenate([self.perturbed, self.clean], axis=1),
            np.concatenate([self.labels, nothing], axis=1),
            np.concatenate([nothing, self.labels], axis=1),
        )


@dataclass(frozen=True)
class Metric:
    """A per-episode metric: `compute(batch, settings)` returns (N,) float64 values."""

    higher_is_better: bool
    compute: Callable[[EpisodeBatch, MetricsConfig], np.ndarray]
    description: str = ""


def lift(raw: np.ndarray, null: np.ndarray) -> np.ndarray:
    """lift_over_null = raw_auroc − null_auroc, per episode."""
    return raw - null


def adjusted(raw: np.ndarray, null: np.ndarray) -> np.ndarray:
    """adjusted_auroc = clip(raw_auroc − null_auroc + 0.5, 0, 1), per episode."""
    return np.clip(raw - null + 0.5, 0.0, 1.0)


#: Metrics defined from a raw (perturbed) and a null (clean) per-episode value, bootstrapped paired.
PAIRED_METRICS: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "lift_over_null": lift,
    "adjusted_auroc": adjusted,
}

#: What `null_episode_metrics` reports: the clean scores against the counterfactual labels.
NULL_METRICS: tuple[str, ...] = (
    "clean_alarm_rate",
    "clean_episode_alarm",
    "detection_delay",
    "f1",
    "null_auprc",
    "null_auroc",
    "precision",
    "recall",
)


def _raw_auroc(b: EpisodeBatch, s: MetricsConfig) -> np.ndarray:
    return auroc_rows(b.perturbed, b.labels)


def _null_auroc(b: EpisodeBatch, s: MetricsConfig) -> np.ndarray:
    return auroc_rows(b.clean, b.labels)


RAW_AUROC = Metric(True, _raw_auroc, "AUROC of z̃ against y over the whole perturbed trajectory")
RAW_AUPRC = Metric(
    True,
    lambda b, s: average_precision_rows(b.perturbed, b.labels),
    "average precision of z̃ against y over the whole perturbed trajectory",
)
# On clean data a null score above chance means the detector reacts to time, not to the anomaly.
NULL_AUROC = Metric(False, _null_auroc, "AUROC of the clean z against the counterfactual y")
NULL_AUPRC = Metric(
    False,
    lambda b, s: average_precision_rows(b.clean, b.labels),
    "average precision of the clean z against the counterfactual y",
)
LIFT_OVER_NULL = Metric(
    True, lambda b, s: lift(_raw_auroc(b, s), _null_auroc(b, s)), "raw_auroc − null_auroc"
)
ADJUSTED_AUROC = Metric(
    True,
    lambda b, s: adjusted(_raw_auroc(b, s), _null_auroc(b, s)),
    "clip(raw_auroc − null_auroc + 0.5, 0, 1)",
)
MATCHED_AUROC = Metric(
    True, lambda b, s: auroc_rows(*b.matched()), "AUROC of z̃[P] (positives) against z[P]"
)
MATCHED_AUPRC = Metric(
    True,
    lambda b, s: average_precision_rows(*b.matched()),
    "average precision of z̃[P] (positives) against z[P]",
)
MATCHED_FPR95 = Metric(
    False,
    lambda b, s: fpr_at_tpr_rows(*b.matched(), tpr_target=s.tpr_target),
    "FPR of z[P] at TPR tpr_target of z̃[P] on the interpolated ROC (ties at τ count a fraction)",
)
PRECISION = Metric(
    True, lambda b, s: precision_recall_f1(b.alarms, b.labels)[0], "alarm precision (0 if none)"
)
RECALL = Metric(True, lambda b, s: precision_recall_f1(b.alarms, b.labels)[1], "alarm recall")
F1 = Metric(True, lambda b, s: precision_recall_f1(b.alarms, b.labels)[2], "alarm F1")
CLEAN_ALARM_RATE = Metric(
    False, lambda b, s: alarm_rate(b.clean_alarms), "fraction of clean steps with an alarm"
)
CLEAN_EPISODE_ALARM = Metric(
    False,
    lambda b, s: b.clean_alarms.any(axis=1).astype(np.float64),
    "1 if a clean episode has any alarm, else 0 (mean: the episode false-alarm rate)",
)
DETECTION_DELAY = Metric(
    False,
    lambda b, s: detection_delay(b.alarms, b.onset, b.latency),
    "first raise time t + latency ≥ t* of an alarm at t, minus t*; T − t* if none",
)
SEGMENT_PRECISION = Metric(
    True,
    lambda b, s: segment_precision_recall(b.alarms, b.onset, b.offset)[0],
    "alarm runs overlapping [t*, offset) / alarm runs (0 if none)",
)
SEGMENT_RECALL = Metric(
    True,
    lambda b, s: segment_precision_recall(b.alarms, b.onset, b.offset)[1],
    "1 if an alarm run overlaps [t*, offset), else 0",
)
TEMPORAL_AUROC = Metric(
    True,
    lambda b, s: temporal_auroc_rows(b.perturbed, b.labels, s.temporal_buffer),
    "range-based AUROC (Paparrizos et al. 2022) of z̃ against y",
)
#: Opt-in (`oodrl.config.OPT_IN_METRICS`): computed where params list it in `metrics.extra`.
VUS_PR = Metric(
    True,
    lambda b, s: vus_pr_rows(b.perturbed, b.labels, s.temporal_buffer),
    "VUS-PR (Paparrizos et al. 2022; TSB-AD) of z̃ against y over buffers 0..temporal_buffer",
)


def _scores(values: np.ndarray, which: str, detector: str) -> np.ndarray:
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2:
        raise ContractError(f"{which} scores must be (N, T); got shape {values.shape}.")
    finite = np.isfinite(values).all(axis=1)
    if not finite.all():
        episode = int(np.argmin(finite))
        raise DetectorError(
            f"Detector '{detector or '?'}' gave NaN or infinite scores on {which} episode "
            f"{episode} (of {len(values)}); scores must be finite — check the detector's "
            f"fit and its inputs."
        )
    return values


def _batch(
    perturbed: np.ndarray,
    clean: np.ndarray,
    labels: np.ndarray,
    threshold: float,
    onset: int,
    offset: int | None,
    latency: int,
) -> EpisodeBatch:
    labels = np.asarray(labels)
    if labels.dtype != bool or labels.shape != perturbed.shape or clean.shape != perturbed.shape:
        raise ContractError(
            "perturbed, clean and labels must share one shape (N, T), labels bool; got "
            f"{perturbed.shape}, {clean.shape}, {labels.dtype} {labels.shape}."
        )
    if perturbed.shape[0] == 0:
        raise ContractError("Metrics need at least one episode; got N = 0.")
    if threshold is None or np.isnan(threshold):
        raise ContractError(f"The alarm threshold must be a number; got {threshold!r}.")
    T = perturbed.shape[1]  # noqa: N806 - the protocol's name for the horizon
    end = T if offset is None else offset
    if not 0 <= onset < end <= T:
        raise ContractError(f"Need 0 <= onset < offset <= T={T}; got {onset}, {offset}.")
    if latency < 0:
        raise ContractError(f"A detector's latency must be >= 0 steps; got {latency}.")
    return EpisodeBatch(
        perturbed, clean, labels, float(threshold), int(onset), offset, int(latency)
    )


def _compute(
    batch: EpisodeBatch, settings: MetricsConfig, names: Iterable[str]
) -> dict[str, np.ndarray]:
    n = batch.perturbed.shape[0]
    values: dict[str, np.ndarray] = {}
    for name in names:
        result = np.asarray(METRICS.get(name).compute(batch, settings), dtype=np.float64)
        if result.shape != (n,):
            raise ContractError(
                f"Metric '{name}' returned shape {result.shape}; expected ({n},), one per episode."
            )
        values[name] = result
    return values


def episode_metrics(
    perturbed: np.ndarray,
    clean: np.ndarray,
    labels: np.ndarray,
    threshold: float,
    onset: int,
    offset: int | None,
    settings: MetricsConfig,
    detector: str = "",
    latency: int = 0,
) -> dict[str, np.ndarray]:
    """Every registered metric per episode: name -> (N,) values, names sorted.

    perturbed, clean: (N, T) scores of N paired episodes (row i of both is evaluation episode
    i); labels: (N, T) bool; threshold: the detector's calibrated θ; the anomaly window is
    [onset, offset) with offset None = T; latency: the detector's look-ahead in steps, which
    the detection delay adds to each alarm. NaN or infinite scores raise `DetectorError`
    naming `detector` and the episode.
    """
    batch = _batch(
        _scores(perturbed, "perturbed", detector),
        _scores(clean, "clean", detector),
        labels,
        threshold,
        onset,
        offset,
        latency,
    )
    from oodrl.metrics import computed_metrics

    return _compute(batch, settings, computed_metrics(settings.extra))


def null_episode_metrics(
    clean: np.ndarray,
    labels: np.ndarray,
    threshold: float,
    onset: int,
    offset: int | None,
    settings: MetricsConfig,
    detector: str = "",
    latency: int = 0,
) -> dict[str, np.ndarray]:
    """The null baseline per episode: the clean scores against the counterfactual labels.

    null_auroc, null_auprc, precision, recall, f1 and detection_delay (with the detector's
    `latency`) of the clean alarms against `labels` (same onset as the anomaly), and
    clean_alarm_rate and clean_episode_alarm (all-zero labels: every alarm is false).
    """
    clean = _scores(clean, "clean", detector)
    batch = _batch(clean, clean, labels, threshold, onset, offset, latency)
    return _compute(batch, settings, NULL_METRICS)


def summarise(
    per_episode: Mapping[str, np.ndarray],
    settings: MetricsConfig,
    paired: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None,
    *,
    seed: int,
) -> dict[str, dict[str, float | int]]:
    """metric -> {mean, std, ci_low, ci_high, n_episodes}, sorted by name, rounded to 6 decimals.

    Every metric is resampled with the same episode draws (seeded by `seed`, the run's).
    `paired` maps a name of `PAIRED_METRICS` to (raw, null) per-episode values — e.g.
    raw_auroc of the perturbed episodes and null_auroc of their matched clean ones — which are
    resampled with the same indices; it takes precedence over `per_episode[name]`. The values
    `episode_metrics` returns for those names are already per-episode pairs, so summarising
    them directly gives the same numbers.
    """
    paired = dict(paired or {})
    unknown = sorted(set(paired) - set(PAIRED_METRICS))
    if unknown:
        raise ContractError(
            f"No paired definition for {unknown}; paired metrics: {sorted(PAIRED_METRICS)}."
        )
    options = {"n_boot": settings.n_boot, "ci": settings.ci, "seed": seed}
    summary: dict[str, dict[str, float | int]] = {}
    for name in sorted(set(per_episode) | set(paired)):
        arrays = paired[name] if name in paired else (per_episode[name],)
        for values in arrays:
            if not np.isfinite(np.asarray(values, dtype=np.float64)).all():
                raise ContractError(f"Metric '{name}' has NaN or infinite per-episode values.")
        if name in paired:
            raw, null = paired[name]
            result = paired_bootstrap(raw, null, PAIRED_METRICS[name], **options)
        else:
            result = episode_bootstrap(per_episode[name], **options)
        summary[name] = result.as_dict()
    return summary


def interquartile_mean(values: np.ndarray, axis: int | None = -1) -> np.ndarray:
    """The mean of the middle 50% (25% trimmed from each end), as scipy's trim_mean."""
    from scipy.stats import trim_mean

    return trim_mean(values, 0.25, axis=axis)
