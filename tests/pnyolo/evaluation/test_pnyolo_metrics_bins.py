"""Figures by distance and box height, on hand-made views."""
from __future__ import annotations

import numpy as np
import pytest

from pnyolo.evaluation.metrics import MetricAccumulator, ViewDetections, ViewGroundTruth
from pnyolo.evaluation.metrics_bins import binned_metrics


def _view(with_distances: bool = True):
    # ground truth: a near tall car (8 m, 30 px), a mid pedestrian (20 m, 16 px, hidden here, seen elsewhere),
    # a far small pedestrian (35 m, 8 px)
    gt = ViewGroundTruth(np.array([[0, 0, 40, 30], [100, 50, 106, 66], [200, 80, 204, 88]], float),
                         np.array([0, 1, 1]), visible_fraction=np.array([1.0, 0.0, 0.5]),
                         seen_elsewhere=np.array([False, True, True]), distances=np.array([8.0, 20.0, 35.0]))
    det = ViewDetections(np.array([[0, 0, 40, 30],        # finds the car
                                   [100, 50, 106, 66],    # finds the hidden pedestrian
                                   [300, 10, 340, 40]]),  # a ghost: 30 px tall, estimated 10 m away
                         np.array([0.9, 0.8, 0.7]), np.array([0, 1, 0]),
                         distances=np.array([8.5, 21.0, 10.0]) if with_distances else None)
    return det, gt


def test_each_bin_counts_its_ground_truth_and_the_false_positives_its_estimate_places_there():
    bins = binned_metrics([_view()], 0.2, num_classes=2)
    near, mid, far = (bins["distance"][k] for k in ("0-13 m", "13-25 m", "25-40 m"))
    assert (near["n"], near["recall"], near["precision"], near["f1"]) == (1, 1.0, 0.5, pytest.approx(2 / 3))
    assert (mid["recall"], mid["precision"], mid["hidden_seen_recall"], mid["n_hidden_seen"]) == (1.0, 1.0, 1.0, 1)
    assert (far["recall"], far["f1"], far["ap50"]) == (0.0, 0.0, 0.0)
    assert near["ap50"] == pytest.approx(1.0, abs=0.01)  # the TP outranks the ghost
    small, medium, tall = (bins["height"][k] for k in ("< 12 px", "12-24 px", ">= 24 px"))
    assert (small["n"], small["recall"]) == (1, 0.0) and (medium["recall"], medium["precision"]) == (1.0, 1.0)
    assert (tall["recall"], tall["precision"]) == (1.0, 0.5)  # the ghost is 30 px tall


def test_without_distance_estimates_only_recall_is_given_by_distance():
    bins = binned_metrics([_view(with_distances=False)], 0.2, num_classes=2)
    near = bins["distance"]["0-13 m"]
    assert near["recall"] == 1.0 and near["f1"] is None and near["ap50"] is None and near["precision"] is None
    assert bins["height"][">= 24 px"]["f1"] == pytest.approx(2 / 3)  # heights are always known


def test_the_summary_carries_the_bins_and_bin_totals_add_up():
    acc = MetricAccumulator([0.2, 0.5], num_classes=2)
    for _ in range(3):
        acc.add(*_view())
    s = acc.summary()
    assert sum(b["n"] for b in s["by_bin"]["height"].values()) == s["ground_truth"] == 9
    tp = sum(round(b["recall"] * b["n"]) for b in s["by_bin"]["height"].values())
    assert tp == s["strict"]["0.2"]["tp"]
