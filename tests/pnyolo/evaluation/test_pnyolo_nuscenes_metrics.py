"""The ground-plane metrics are the nuScenes devkit's (accumulate, calc_ap, calc_tp on EvalBoxes built from our
splits): the ground truth scored against itself is perfect, a copy moved 1.5 m loses exactly the thresholds below
1.5 m, and the hand-written centre-distance AP they replaced differed from them (issue 65)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_pnyolo_common import TINY

from dataset_spec.nuscenes_format import attribute_of
from dataset_spec.synthetic import write_synthetic_dataset
from pnyolo.config import load_config
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.decoding.detections import ViewDetections
from pnyolo.evaluation.evaluate import scored_views
from pnyolo.evaluation.metrics_3d import metrics_3d
from tools.projection import label_dataset

pytest.importorskip("nuscenes")


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    """Every scored view of a synthetic sequence's test split: (the ground truth as detections, the ground truth)."""
    root = write_synthetic_dataset(tmp_path_factory.mktemp("nm") / "ds", n_scenarios=3, frames=3, fps=2.0)
    label_dataset(root, progress=False)
    data = MultiViewDataset(root, "test", load_config(None, TINY), every_camera=True)
    out = []
    for k in range(len(data)):
        item = data[k]
        for _, _, gt in scored_views(item, [None] * len(item.images)):
            names = [data.class_names[int(c)] for c in gt.classes]
            attributes = [attribute_of(n, float(np.hypot(*v)), False) for n, v in zip(names, gt.velocities)]
            out.append((ViewDetections(gt.boxes, np.ones(len(gt.boxes)), gt.classes, centres=gt.centres,
                                       world_boxes=gt.world_boxes, velocities=gt.velocities, attributes=attributes), gt))
    assert sum(len(g.boxes) for _, g in out) > 20 and all(np.isfinite(g.velocities).all() for _, g in out)
    return out, data.class_names


def test_the_ground_truth_against_itself_scores_map_1_and_every_error_0(records):
    recs, names = records
    kit = metrics_3d(recs, names)["per_view"]
    assert kit["map"] == pytest.approx(1.0) and kit["nds"] == pytest.approx(1.0)
    assert all(v == pytest.approx(0.0, abs=1e-9) for v in kit["errors"].values()), kit["errors"]


def test_a_copy_moved_1_5_m_misses_below_1_5_m_and_hits_above(records):
    recs, names = records
    moved = []
    for det, gt in recs:
        shift = np.array([1.5, 0.0, 0.0])
        boxes = det.world_boxes.copy()
        boxes[:, :3] += shift
        moved.append((replace(det, centres=det.centres + shift, world_boxes=boxes), gt))
    ap = metrics_3d(moved, names)["per_view"]["ap"]
    assert (ap["0.5"]["mean"], ap["1"]["mean"]) == (0.0, 0.0)
    assert ap["2"]["mean"] == pytest.approx(1.0) and ap["4"]["mean"] == pytest.approx(1.0)
    errors = metrics_3d(moved, names)["per_view"]["errors"]
    assert errors["ATE"] == pytest.approx(1.5) and errors["ASE"] == pytest.approx(0.0, abs=1e-9)
