"""Alarm metrics on hand-worked examples."""

import numpy as np
import pytest
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
