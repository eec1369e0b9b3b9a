"""Late fusion's sender calibration: the logistic fit recovers a known law, reports are labelled by the 3D
ground truth one road user each, and calibrated scores follow the sender's distance."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from pnyolo.decoding.detections import WorldDetections
from pnyolo.cooperation.calibration import (calibrate_scores, calibrated, fit_calibration, report_labels,
                                           sender_distances)


def _dets(xy, scores, classes):
    boxes = np.zeros((len(xy), 7))
    boxes[:, :2] = xy
    boxes[:, 3:6] = (4.0, 1.8, 1.5)
    return WorldDetections(boxes, np.asarray(scores, np.float64), np.asarray(classes, np.int64))


def test_the_fit_recovers_a_known_law_and_without_both_labels_keeps_the_scores():
    rng = np.random.default_rng(0)
    s, d = rng.uniform(0.02, 0.98, 40000), rng.uniform(0, 40, 40000)
    law = (1.5, -0.8, 0.3)
    y = (rng.uniform(size=len(s)) < calibrate_scores(s, d, law)).astype(float)
    assert np.allclose(fit_calibration(s, d, y), law, atol=0.06)
    assert fit_calibration(s, d, np.ones_like(s)) == (1.0, 0.0, 0.0)
    assert np.allclose(calibrate_scores(s, d, (1.0, 0.0, 0.0)), s)  # the identity law


def test_a_fit_on_separated_reports_stays_of_the_features_order():
    """Reports whose score alone tells true from false (every true one scored above 0.95) are fitted to a steep law of
    bounded coefficients, not run off towards infinity (as 8.7e6 once was)."""
    rng = np.random.default_rng(1)
    s, d = rng.uniform(0.01, 0.9999, 38000), rng.uniform(0, 40, 38000)
    y = (s > 0.95).astype(float)
    coef = fit_calibration(s, d, y)
    assert max(abs(c) for c in coef) < 50, coef
    chance = calibrate_scores(np.array([0.999, 0.5]), np.array([10.0, 10.0]), coef)
    assert chance[0] > 0.9 and chance[1] < 0.05, chance


def test_reports_are_labelled_one_road_user_each_by_class_and_distance():
    item = SimpleNamespace(boxes_3d=torch.tensor([[10.0, 0, 0.75, 4, 1.8, 1.5, 0], [20.0, 5, 0.9, 0.6, 0.6, 1.8, 0]]),
                           box_classes=torch.tensor([0, 1]))
    dets = _dets([[10.3, 0.1], [10.0, 0.4], [20.0, 5.0], [30.0, 0.0]], [0.4, 0.9, 0.5, 0.8], [0, 0, 0, 0])
    # the car at 10 m goes to the better of its two reports; a car report on the pedestrian and one far from
    # every road user are false
    assert report_labels(dets, item, 1.0).tolist() == [0.0, 1.0, 0.0, 0.0]


def test_calibrated_scores_use_each_sender_s_own_camera():
    c2w = torch.eye(4).repeat(2, 1, 1)
    c2w[1, :3, 3] = torch.tensor([30.0, 0.0, 1.5])
    item = SimpleNamespace(camera_to_world=c2w)
    cars = [_dets([[10.0, 0.0]], [0.5], [0]), _dets([[10.0, 0.0]], [0.5], [0]), WorldDetections.empty()]
    assert np.allclose(sender_distances(item, 1, cars[1]), [20.0])
    near, far, empty = calibrated(cars, item, (1.0, -1.0, 0.0))
    assert np.allclose(near.scores, 1 / (1 + np.exp(1.0))) and np.allclose(far.scores, 1 / (1 + np.exp(2.0)))
    assert len(empty) == 0 and np.array_equal(near.boxes, cars[0].boxes)
    assert calibrated(cars, item, None) is cars
