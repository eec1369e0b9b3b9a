"""Issue 6 pieces: single-view baseline learns, fusion, the single-view ceiling, pnyolo-eval --fuse."""
from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from test_pnyolo_common import make_dataset, tiny

from dataset_spec import Dataset
from dataset_spec.boxes import box_to_yolo
from pnyolo.cli import eval_main
from pnyolo.config import load_config
from pnyolo.training.train import train
from pnyolo.data.item import Item
from pnyolo.evaluation.evaluate import spread_over_scenarios
from pnyolo.evaluation.fusion import fuse_detections
from pnyolo.evaluation.metrics import MetricAccumulator, ViewDetections, ViewGroundTruth, single_view_ceiling

torch.set_num_threads(2)

@pytest.fixture(scope="module")
def tiny_ds(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("cmp") / "ds", n_scenarios=3)


def _dets(boxes, scores, classes, dist=None):
    return ViewDetections(np.array(boxes, float).reshape(-1, 4), np.array(scores, float), np.array(classes, int),
                          None if dist is None else np.array(dist, float))


def test_fusing_identical_prediction_sets_changes_nothing():
    a = _dets([[0, 0, 10, 10], [8, 0, 18, 10], [30, 30, 40, 45]], [0.9, 0.6, 0.7], [0, 0, 1], [5.0, 6.0, 7.0])
    fused = fuse_detections(a, a, nms_iou=0.5)
    for field in ("boxes", "scores", "classes", "distances"):
        np.testing.assert_array_equal(getattr(fused, field), getattr(a, field))


def test_fusion_is_the_union_after_nms():
    multi = _dets([[0, 0, 10, 10], [50, 50, 60, 70]], [0.8, 0.5], [0, 1], [12.0, 20.0])  # 2nd: hidden object
    single = _dets([[1, 0, 11, 10], [100, 0, 110, 5]], [0.95, 0.9], [0, 0])  # no distances
    fused = fuse_detections(multi, single, nms_iou=0.5)
    assert len(fused.boxes) == 3  # the overlapping pair collapses to the higher score
    assert sorted(fused.scores.tolist()) == [0.5, 0.9, 0.95]
    assert np.isnan(fused.distances[fused.scores == 0.95]).all() and fused.distances[fused.scores == 0.5] == [20.0]
    empty = _dets([], [], [])
    assert len(fuse_detections(empty, empty, 0.5).boxes) == 0


def test_single_view_ceiling_on_hand_made_labels():
    assert single_view_ceiling([0.0, 0.0, 0.3, 1.0]) == {"recall_ceiling": 0.5, "n": 4, "fully_hidden": 2}
    assert single_view_ceiling([])["recall_ceiling"] is None
    assert single_view_ceiling([np.nan, 0.5])["recall_ceiling"] == 1.0  # not measured: left out
    acc = MetricAccumulator([0.5])
    gt = ViewGroundTruth(np.array([[0, 0, 10, 10], [20, 20, 30, 30.0]]), np.array([0, 0]), np.array([0.0, 0.9]))
    acc.add(_dets([[0, 0, 10, 10], [20, 20, 30, 30]], [0.9, 0.8], [0, 0]), gt)
    s = acc.summary()
    assert s["single_view_ceiling"]["recall_ceiling"] == 0.5
    assert s["strict"]["0.5"]["recall"] == 1.0  # a multi-view detector may exceed the ceiling


class _HandMadeItems:
    """Views of a 160x96 image (10x6 grid) with hand-placed labels (boxes, classes, visible fractions and
    optionally distances, default 10 m), shaped like MultiViewDataset items."""

    class_names = ["car", "pedestrian"]

    def __init__(self, views, fallback=True):
        from pnyolo.data.grid import GridSpec
        from pnyolo.data.targets import build_targets

        self.anchors = torch.tensor([[0.05, 0.2], [0.2, 0.1], [0.4, 0.3]])
        g = GridSpec(160, 96, 10, 6)
        targets, gts = [], []
        for boxes, classes, vis, *dist in views:
            boxes = np.array(boxes, float)
            dist = np.array(dist[0] if dist else np.full(len(boxes), 10.0), float)
            yolo = torch.tensor(np.stack([box_to_yolo(b, g.width, g.height) for b in boxes]), dtype=torch.float32)
            targets.append(build_targets(yolo, torch.tensor(classes), g.grid_h, g.grid_w, self.anchors,
                                         fallback=fallback, extras=torch.stack([
                                             torch.ones(len(dist)), torch.tensor(dist, dtype=torch.float32),
                                             torch.zeros(len(dist))], dim=1)))
            gts.append(ViewGroundTruth(boxes, np.array(classes), np.array(vis, float), np.ones(len(boxes), bool), dist))
        self.item = Item(None, None, None, g, [], [], list(range(len(gts))), gt=gts)
        stacked = torch.stack(targets)
        self.model = SimpleNamespace(anchors=self.anchors, targets=lambda item: stacked)  # a YOLO-grid kind's part

    def __len__(self):
        return 1

    def __getitem__(self, k):
        return self.item


def _ceiling(items, nms_iou: float, depth_gap: float | None = None):
    from pnyolo.evaluation.evaluate import encoding_ceiling

    return encoding_ceiling(items.model, items, SimpleNamespace(nms_iou=nms_iou, depth_gap=depth_gap))


def test_encoding_ceiling_counts_what_targets_and_nms_lose():
    from pnyolo.evaluation.metrics import HIDDEN_SEEN_ELSEWHERE as HIDDEN_SEEN

    # view 0: a car and a pedestrian hidden behind it share one grid cell (boxes barely overlap):
    # both keep a target slot, both survive NMS. View 1: a car exactly behind a same-sized car:
    # its own slot (next-best anchor), but NMS at 0.45 keeps only one of the two boxes.
    views = [([[40, 40, 72, 52], [52, 30, 60, 60]], [0, 1], [1.0, 0.0]),
             ([[40, 40, 72, 52], [41, 41, 73, 53]], [0, 0], [1.0, 0.0])]
    items = _HandMadeItems(views)
    ceiling = _ceiling(items, nms_iou=0.45)
    assert ceiling.n == 4 and ceiling.recall == pytest.approx(0.75)
    assert ceiling.breakdown[HIDDEN_SEEN]["n"] == 2
    assert ceiling.hidden_seen_recall() == ceiling.breakdown[HIDDEN_SEEN]["recall"]
    assert ceiling.as_json()["breakdown"] == ceiling.breakdown and ceiling.as_json()["nms_iou"] == 0.45
    assert _ceiling(items, nms_iou=0.95).recall == pytest.approx(1.0)
    # without the anchor fallback the second car of view 1 has no slot: lost even without NMS
    no_fallback = _HandMadeItems(views, fallback=False)
    assert _ceiling(no_fallback, nms_iou=0.95).recall == pytest.approx(0.75)
    # depth-gated NMS with exact distances keeps the car 8 m behind the other, not one 1 m behind it
    apart = _HandMadeItems([views[0], (*views[1], [10.0, 18.0])])
    assert _ceiling(apart, nms_iou=0.45, depth_gap=4.0).recall == pytest.approx(1.0)
    assert _ceiling(apart, nms_iou=0.45).recall == pytest.approx(0.75)
    close = _HandMadeItems([views[0], (*views[1], [10.0, 11.0])])
    assert _ceiling(close, nms_iou=0.45, depth_gap=4.0).recall == pytest.approx(0.75)


def test_distance_error_skips_detections_without_a_distance():
    acc = MetricAccumulator([0.5])
    gt = ViewGroundTruth(np.array([[0, 0, 10, 10], [20, 20, 30, 30.0]]), np.array([0, 0]), distances=np.array([10.0, 20.0]))
    acc.add(_dets([[0, 0, 10, 10], [20, 20, 30, 30]], [0.9, 0.8], [0, 0], [12.0, np.nan]), gt)
    assert acc.distance_error(0.5) == {"mean_abs_m": 2.0, "n": 1}
    single = MetricAccumulator([0.5])
    single.add(_dets([[0, 0, 10, 10]], [0.9], [0], [np.nan]), gt)
    assert single.summary()["distance_error"] == {"mean_abs_m": None, "n": 0}
    json.dumps(single.summary(), allow_nan=False)  # reports stay strict JSON


def test_distance_error_compares_with_the_matched_object_not_the_most_overlapping_one():
    # a pedestrian detection overlaps the car box more, but matches (class-aware) the pedestrian
    gt = ViewGroundTruth(np.array([[0, 0, 10, 20], [2, 0, 12, 20.0]]), np.array([0, 1]), distances=np.array([30.0, 8.0]))
    acc = MetricAccumulator([0.5])
    acc.add(_dets([[2, 0, 12, 20]], [0.9], [0], [29.0]), gt)
    assert acc.distance_error(0.5) == {"mean_abs_m": 1.0, "n": 1}


def _losses(run):
    return [r["loss"] for r in map(json.loads, (run / "log.jsonl").read_text().splitlines()) if r["event"] == "step"]


def test_single_view_model_loss_falls(tiny_ds, tmp_path):
    cfg = load_config(None, tiny("model.kind=single-view", "train.max_steps=60", "train.epochs=1000",
                                    "train.lr=0.001", "train.lr_decay=1.0", "train.log_every=1", "data.color_jitter=false"))
    train(tiny_ds, cfg, tmp_path / "sv", quiet=True)
    losses = _losses(tmp_path / "sv")
    assert len(losses) == 60
    assert np.mean(losses[-10:]) < 0.7 * np.mean(losses[:10]), (losses[:10], losses[-10:])


def test_eval_fuse_reports_both_models_and_their_union(tiny_ds, tmp_path, capsys):
    runs = {}
    for kind in ("pixelnerf-yolo", "single-view"):
        cfg = load_config(None, tiny(f"model.kind={kind}", "train.max_steps=2", "train.epochs=1"))
        train(tiny_ds, cfg, tmp_path / kind, quiet=True)
        runs[kind] = tmp_path / kind / "latest.pt"
    out = tmp_path / "cmp"
    rc = eval_main([str(runs["pixelnerf-yolo"]), str(tiny_ds), "--fuse", str(runs["single-view"]), "--views", "0,1,2",
                    "--conf", "0.0", "--out", str(out)])
    assert rc == 0
    report = json.loads((out / "comparison.json").read_text())
    models = report["models"]
    assert set(models) == {"pixelnerf-yolo", "single-view", "fusion"}
    assert models["fusion"]["predictions"] <= models["pixelnerf-yolo"]["predictions"] + models["single-view"]["predictions"]
    assert models["fusion"]["ground_truth"] == models["single-view"]["ground_truth"] > 0
    assert (out / "comparison.md").read_text().count("|") > 10 and (out / "f1_vs_match_iou.png").is_file()
    assert (out / "single-view" / "metrics.json").is_file()
    # fusing with a checkpoint trained on another grid is refused in one line
    cfg = load_config(None, tiny("model.kind=single-view", "train.max_steps=1", "train.epochs=1", "data.cell_px=16"))
    train(tiny_ds, cfg, tmp_path / "other", quiet=True)
    capsys.readouterr()
    rc = eval_main([str(runs["pixelnerf-yolo"]), str(tiny_ds), "--fuse", str(tmp_path / "other" / "latest.pt")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "cell_px" in err
    # depth-gated NMS keeps at least what plain NMS keeps; a gap that is not positive is refused in one line
    rc = eval_main([str(runs["pixelnerf-yolo"]), str(tiny_ds), "--views", "0,1,2", "--conf", "0.0", "--depth-gap", "2",
                    "--out", str(tmp_path / "gap")])
    gated = json.loads((tmp_path / "gap" / "metrics.json").read_text())
    assert rc == 0 and gated["predictions"] >= models["pixelnerf-yolo"]["predictions"]
    capsys.readouterr()  # that run's progress bar
    rc = eval_main([str(runs["pixelnerf-yolo"]), str(tiny_ds), "--depth-gap", "0"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "--depth-gap" in err


def test_ceiling_matches_the_dataset_labels(tiny_ds):
    ds = Dataset.open(tiny_ds)
    vis = [o.visible_fraction for s in ds.scenario_names() for c in ds.scenario(s).cameras
           for o in ds.read_labels(s, c.name).kept()]
    ceiling = single_view_ceiling(vis)
    assert ceiling["n"] == len(vis) > 0
    assert ceiling["recall_ceiling"] == pytest.approx(np.mean(np.array(vis) > 0))


def test_items_visited_one_per_scenario_first():
    items = [("a", "noon"), ("a", "dusk"), ("b", "noon"), ("b", "dusk"), ("c", "noon")]
    assert [items[k] for k in spread_over_scenarios(items)] == [
        ("a", "noon"), ("b", "noon"), ("c", "noon"), ("a", "dusk"), ("b", "dusk")]
    assert sorted(spread_over_scenarios(items)) == list(range(len(items)))  # every item exactly once
