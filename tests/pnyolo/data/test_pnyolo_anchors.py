"""Anchors fitted to labels: clusters are recovered, and they beat a generic set on the data."""
from __future__ import annotations

import numpy as np
from test_pnyolo_common import make_dataset

from dataset_spec import Dataset
from pnyolo.data.anchors import anchors_from_labels, kmeans_anchors, wh_iou


def test_kmeans_recovers_three_box_shapes():
    rng = np.random.default_rng(0)
    centres = np.array([[0.02, 0.08], [0.1, 0.07], [0.3, 0.2]])  # pedestrian-, car-, near-car-like
    wh = np.concatenate([c * rng.uniform(0.9, 1.1, (200, 2)) for c in centres])
    anchors = kmeans_anchors(wh, 3)
    np.testing.assert_allclose(anchors, centres, rtol=0.06)
    assert np.all(np.diff(anchors.prod(axis=1)) > 0)  # sorted by area


def test_fitted_anchors_fit_the_labels_better_than_generic_ones(tmp_path):
    root = make_dataset(tmp_path / "ds", n_scenarios=2, width=96, height=72)
    ds = Dataset.open(root)
    names = ds.scenario_names()
    anchors = np.array(anchors_from_labels(ds, names, k=3))
    wh = np.array([((o.box[2] - o.box[0]) / 96, (o.box[3] - o.box[1]) / 72) for s in names
                   for c in ds.scenario(s).cameras for o in ds.read_labels(s, c.name).kept()])
    generic = np.array([[0.02, 0.03], [0.04, 0.07], [0.08, 0.06]])  # the original code's first set
    assert wh_iou(wh, anchors).max(1).mean() > wh_iou(wh, generic).max(1).mean() + 0.1
