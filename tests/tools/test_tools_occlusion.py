"""Occlusion statistics: bins, 'seen by another camera', JSON output."""
from __future__ import annotations

import json

import numpy as np

from dataset_spec import Label2D, LabelThresholds, ViewLabels
from tools.occlusion import format_statistics, occlusion_statistics, visibility_bin
from tools.projection import kitti_occlusion_level


def lab(iid, visible, cls="car", amodal=100):
    return Label2D(iid, cls, np.array([0.0, 0, 10, 10]), 1.0, visible, 10.0, int(visible * amodal), amodal,
                   kitti_occlusion_level(visible, amodal > 0))


def view(scenario, camera, labels):
    return ViewLabels(scenario, camera, 64, 48, LabelThresholds(), labels)


def test_bins_match_kitti_levels():
    for v, name, level in [(0.0, "fully_hidden", 2), (0.39, "mostly_hidden", 2), (0.4, "partly_hidden", 1),
                           (0.79, "partly_hidden", 1), (0.8, "visible", 0), (1.0, "visible", 0)]:
        assert visibility_bin(v) == name and kitti_occlusion_level(v) == level


def test_counts_and_seen_elsewhere():
    labels = [
        view("s1", "a", [lab(2, 0.0), lab(3, 0.2, "pedestrian"), lab(4, 0.9), lab(5, 0.0)]),
        view("s1", "b", [lab(2, 0.5), lab(3, 0.1, "pedestrian"), lab(4, 0.6), lab(6, 0.3, amodal=0)]),
        view("s2", "a", [lab(5, 0.95)]),  # same id, other scenario: must not count for s1's actor 5
    ]
    s = occlusion_statistics(labels)
    assert s["pairs"] == 9 and s["unmeasured"] == 1
    assert (s["fully_hidden"], s["mostly_hidden"], s["partly_hidden"], s["visible"]) == (2, 2, 2, 2)
    assert s["hidden"] == 4
    assert s["hidden_seen_elsewhere"] == 1  # only actor 2 (0.5 in camera b); 3 is hidden in both, 5 only in s2
    assert s["hidden_seen_elsewhere_fraction"] == 0.25
    assert s["per_class"]["pedestrian"]["mostly_hidden"] == 2 and s["per_class"]["pedestrian"]["hidden_seen_elsewhere"] == 0
    assert json.loads(json.dumps(s)) == s
    assert "hidden but seen by another camera: 1 (25%)" in format_statistics(s)


def test_empty_input():
    s = occlusion_statistics([])
    assert s["pairs"] == 0 and s["hidden_seen_elsewhere_fraction"] is None and s["per_class"] == {}
    json.dumps(s)


def test_statistics_of_a_labelled_synthetic_dataset(synthetic_dataset):
    from dataset_spec import Dataset
    from tools.projection import label_scenario

    ds = Dataset.open(synthetic_dataset)
    labels = [vl for name in ds.scenario_names() for vl in label_scenario(ds, name, write=False)]
    s = occlusion_statistics(labels)
    assert s["pairs"] == sum(len(v.objects) for v in labels) > 0
    assert s["pairs"] == sum(s[b] for b in ("fully_hidden", "mostly_hidden", "partly_hidden", "visible", "unmeasured"))
    assert s["fully_hidden"] > 0  # the toy scenes hide cars behind the wall
