"""Alarm metrics of SPEC §6, computed from boolean alarms (score ≥ threshold) per episode.

Every function takes `alarms` (N, T) bool, one row per episode (a 1-D array is one row), and
returns (N,) float64. Degenerate cases are defined: no alarms → precision 0; no positives →
recall 0; precision and recall both 0 → F1 0; no alarm segments → segment precision 0.
"""

from __future__ import annotations

import numpy as np

from oodrl.errors import ContractError


def _alarm_rows(alarms: np.ndarray) -> np.ndarray:
    alarms = np.atleast_2d(np.asarray(alarms))
    if alarms.dtype != bool or alarms.ndim != 2:
        raise ContractError(f"alarms must be bool (N, T); got {alarms.dtype} {alarms.shape}.")
    return alarms


def _window(T: int, onset: int, offset: int | None) -> tuple[int, int]:  # noqa: N803
    end = T if offset is None else offset
    if not 0 <= onset <= end <= T:
        raise ContractError(f"Need 0 <= onset <= offset <= T={T}; got {onset}, {offset}.")
    return onset, end


def precision_recall_f1(
    alarms: np.ndarray, labels: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step-wise precision, recall and F1 of the alarms against boolean labels."""
    alarms = _alarm_rows(alarms)
    labels = np.atleast_2d(np.asarray(labels, dtype=bool))
    if labels.shape != alarms.shape:
        raise ContractError(f"labels {labels.shape} must match alarms {alarms.shape}.")
    hits = (alarms & labels).sum(axis=1)
    n_alarms = alarms.sum(axis=1)
    n_positive = labels.sum(axis=1)
    precision = np.where(n_alarms > 0, hits / np.maximum(n_alarms, 1), 0.0)
    recall = np.where(n_positive > 0, hits / np.maximum(n_positive, 1), 0.0)
    total = precision + recall
    f1 = np.where(total > 0, 2 * precision * recall / np.where(total > 0, total, 1.0), 0.0)
    return precision, recall, f1


def alarm_rate(alarms: np.ndarray) -> np.ndarray:
    """Fraction of steps with an alarm (the clean alarm rate when run on clean scores)."""
    return _alarm_rows(alarms).mean(axis=1)


def detection_delay(alarms: np.ndarray, onset: int, latency: int = 0) -> np.ndarray:
    """Steps from the onset t* to the first alarm the detector could have raised at or after it.

    An alarm on the score of step t is raised at step t + latency (the detector's look-ahead,
    `BaseDetector.latency`): a score that uses s_{t+1} is not known before t + 1. The delay is
    the first raise time ≥ t* minus t*, so an alarm at t ≥ t* − latency counts. A raise time at
    or after T (beyond the recorded stream) counts as no alarm: T − t*, the largest delay.
    """
    alarms = _alarm_rows(alarms)
    T = alarms.shape[1]  # noqa: N806 - the protocol's name for the horizon
    _window(T, onset, None)
    if latency < 0:
        raise ContractError(f"latency must be >= 0 steps; got {latency}.")
    first_counted = max(onset - latency, 0)
    after = alarms[:, first_counted:]
    raised = first_counted + np.argmax(after, axis=1) + latency
    raised = np.where(after.any(axis=1), np.minimum(raised, T), T)
    return (raised - onset).astype(np.float64)


def segment_precision_recall(
    alarms: np.ndarray, onset: int, offset: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Segment precision and recall of runs of consecutive alarms against [onset, offset).

    A segment (maximal run of alarms) is a hit when it overlaps the anomaly window.
    Precision = hits / segments (0 without segments); recall = 1 if any segment hits, else 0.
    """
    alarms = _alarm_rows(alarms)
    start, end = _window(alarms.shape[1], onset, offset)
    previous = np.zeros_like(alarms)
    previous[:, 1:] = alarms[:, :-1]
    segment_starts = alarms & ~previous
    # A hit segment has exactly one first alarm inside the window: where it starts, or at the
    # window's first step when it began before the window.
    first_inside = segment_starts.copy()
    if start < end:
        first_inside[:, start] = alarms[:, start]
    hits = first_inside[:, start:end].sum(axis=1)
    n_segments = segment_starts.sum(axis=1)
    precision = np.where(n_segments > 0, hits / np.maximum(n_segments, 1), 0.0)
    return precision, (hits > 0).astype(np.float64)
