"""Alarm metrics on hand-worked examples."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from sklearn.metrics import f1_score, precision_score, recall_score

from oodrl.errors import ContractError
from oodrl.metrics.alarms import (
    alarm_rate,
    detection_delay,
    precision_recall_f1,
    segment_precision_recall,
)


def bools(text: str) -> np.ndarray:
    """'..##.' -> [F, F, T, T, F]"""
    return np.array([c == "#" for c in text])


def test_precision_recall_f1_hand_worked():
    alarms = bools(".##...##..")
    labels = bools("......####")
    precision, recall, f1 = precision_recall_f1(alarms, labels)
    assert precision[0] == 0.5  # 2 of 4 alarms are on anomaly steps
    assert recall[0] == 0.5  # 2 of 4 anomaly steps have an alarm
    assert f1[0] == 0.5
    assert precision[0] == precision_score(labels, alarms)
    assert recall[0] == recall_score(labels, alarms)
    assert f1[0] == f1_score(labels, alarms)


def test_precision_recall_f1_degenerate_cases():
    precision, recall, f1 = precision_recall_f1(bools("....."), bools("..###"))
    assert (precision[0], recall[0], f1[0]) == (0.0, 0.0, 0.0)
    precision, recall, f1 = precision_recall_f1(bools(".#..."), bools("....."))
    assert (precision[0], recall[0], f1[0]) == (0.0, 0.0, 0.0)


def test_rows_are_independent():
    alarms = np.stack([bools("##.."), bools("..##")])
    labels = np.stack([bools("..##"), bools("..##")])
    precision, recall, _ = precision_recall_f1(alarms, labels)
    np.testing.assert_array_equal(precision, [0.0, 1.0])
    np.testing.assert_array_equal(recall, [0.0, 1.0])
    np.testing.assert_array_equal(alarm_rate(alarms), [0.5, 0.5])


def test_detection_delay_hand_worked():
    assert detection_delay(bools("#....#...."), onset=3)[0] == 2.0  # alarm at 0 is before t*
    assert detection_delay(bools("...#......"), onset=3)[0] == 0.0
    assert detection_delay(bools("##........"), onset=3)[0] == 7.0  # none after t*: T − t*
    assert detection_delay(bools(".........."), onset=0)[0] == 10.0


def test_detection_delay_counts_an_alarm_when_it_could_have_been_raised():
    # A score that looks 2 steps ahead: its alarm at t is raised at t + 2.
    assert detection_delay(bools("#....#...."), onset=3, latency=2)[0] == 4.0
    # An alarm on the score of t* − 2 is raised at t*: delay 0, not "before the onset".
    assert detection_delay(bools(".#........"), onset=3, latency=2)[0] == 0.0
    assert detection_delay(bools("#........."), onset=3, latency=2)[0] == 7.0
    # A raise time beyond the recorded stream counts as no alarm: T − t*.
    assert detection_delay(bools("........#."), onset=3, latency=5)[0] == 7.0
    assert detection_delay(bools("...#......"), onset=3, latency=0)[0] == 0.0
    with pytest.raises(ContractError, match="latency"):
        detection_delay(bools("...#......"), onset=3, latency=-1)


@given(arrays(np.bool_, (3, 30)), st.integers(0, 29), st.integers(0, 6))
def test_detection_delay_is_the_first_raise_time_of_the_alarms(alarms, onset, latency):
    delays = detection_delay(alarms, onset, latency)
    for row, delay in zip(alarms, delays, strict=True):
        raised = [t + latency for t in np.flatnonzero(row) if onset <= t + latency < row.size]
        assert delay == (min(raised) if raised else row.size) - onset
        # Latency can only postpone a detection, never advance it past the look-ahead-free one.
        assert delay <= detection_delay(row, onset, 0)[0] + latency


def test_segment_precision_recall_hand_worked():
    # Segments: [1,3) before the window, [5,7) inside, [8,10) straddling the offset.
    alarms = bools(".##..##.##..")
    precision, recall = segment_precision_recall(alarms, onset=4, offset=9)
    assert precision[0] == pytest.approx(2 / 3)
    assert recall[0] == 1.0
    # A segment that starts before the onset and runs into the window is a hit.
    precision, recall = segment_precision_recall(bools("..####...."), onset=4)
    assert (precision[0], recall[0]) == (1.0, 1.0)
    # Only false segments.
    precision, recall = segment_precision_recall(bools("##.#......"), onset=5)
    assert (precision[0], recall[0]) == (0.0, 0.0)
    # No segments at all.
    precision, recall = segment_precision_recall(bools(".........."), onset=5)
    assert (precision[0], recall[0]) == (0.0, 0.0)


def test_segment_ending_at_the_onset_is_not_a_hit():
    precision, recall = segment_precision_recall(bools("..##......"), onset=4, offset=8)
    assert (precision[0], recall[0]) == (0.0, 0.0)
    precision, _ = segment_precision_recall(bools("........##"), onset=4, offset=8)
    assert precision[0] == 0.0  # starts at the (exclusive) offset


def test_alarms_must_be_bool():
    with pytest.raises(ContractError, match="bool"):
        alarm_rate(np.array([0.0, 1.0]))
    with pytest.raises(ContractError, match="onset"):
        segment_precision_recall(bools("...."), onset=3, offset=2)
