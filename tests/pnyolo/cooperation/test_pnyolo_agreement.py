"""Late fusion by agreement: the reports of one road user by several cars scored together (noisy-OR), so
that what one car alone half-believes can be dropped while what cars agree on stays."""
from __future__ import annotations

import numpy as np
import pytest

from pnyolo.decoding.detections import WorldDetections
from pnyolo.cooperation.agreement import fuse_agreeing, gather, noisy_or
from pnyolo.cooperation.late_fusion import pool_cars
from pnyolo.cooperation.message import CarMessage, fuse_weighted


def _dets(rows):
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, 3)  # x, y, score; class 0, a 4 x 2 m car
    boxes = np.column_stack([rows[:, :2], np.full((len(rows), 5), [0.8, 4.0, 2.0, 1.5, 0.0])])
    return WorldDetections(boxes, rows[:, 2], np.zeros(len(rows), np.int64))


def test_noisy_or_counts_each_car_once_by_its_best_report():
    assert noisy_or(np.array([0.5, 0.6]), np.array([1, 2])) == pytest.approx(1 - 0.5 * 0.4)
    assert noisy_or(np.array([0.5, 0.3]), np.array([7, 7])) == pytest.approx(0.5)  # two cameras of one car
    assert noisy_or(np.array([0.2, 0.5, 0.5]), np.array([1, 1, 2])) == pytest.approx(0.75)


def test_agreeing_cars_stay_and_a_lone_half_belief_goes():
    """Cars 1 and 2 see a road user 0.4 m apart at 0.5 and 0.6 (fused 0.8, hand-computed); car 3 alone
    reports one 10 m away at 0.6 and car 1 alone one at 0.9: kept from 0.7, the agreed one and the sure one stay."""
    a, b, c = _dets([[0, 0, 0.5], [20, 0, 0.9]]), _dets([[0.4, 0, 0.6]]), _dets([[10, 0, 0.6]])
    fused = pool_cars([a, b, c], [1, 2, 3], radius=1.0, keep=0.7)
    assert sorted(fused.scores.round(6)) == [0.8, 0.9]
    agreed = fused.boxes[np.argmin(np.abs(fused.scores - 0.8))]
    assert agreed[0] == pytest.approx(0.4)  # the best report's box
    best_car = pool_cars([a, b, c], [1, 2, 3], radius=1.0)  # the first rule: every road user, the best score
    assert sorted(best_car.scores) == [0.6, 0.6, 0.9] and len(pool_cars([a, b, c], [1, 2, 3], 1.0, keep=0.0)) == 3
    # a road user's reports are grouped exactly as centre NMS groups them: same classes, same boxes kept
    assert np.array_equal(np.sort(fuse_agreeing(WorldDetections.concat([a, b, c]), np.array([1, 1, 2, 3]), 1.0).boxes, 0),
                          np.sort(best_car.boxes, 0))
    other = WorldDetections(b.boxes, b.scores, np.ones(1, np.int64))  # another class at the same place
    assert len(gather(WorldDetections.concat([a, other]), 1.0)) == 3


def test_weighted_fusion_scores_by_agreement_per_sender():
    a = CarMessage(1, 0.0, (0, 0, 0, 0), (0, 0, 0), _dets([[0.0, 5.0, 0.6]]), np.array([[0.1, 0.0, 0.1]]))
    b = CarMessage(2, 0.0, (0, 0, 0, 0), (0, 0, 0), _dets([[1.0, 5.0, 0.8]]), np.array([[0.4, 0.0, 0.4]]))
    assert fuse_weighted([a, b], 2.0).scores[0] == pytest.approx(0.8)
    agreed = fuse_weighted([a, b], 2.0, agreement=True)
    assert agreed.scores[0] == pytest.approx(1 - 0.4 * 0.2) and agreed.boxes[0, 0] == pytest.approx(0.2)
