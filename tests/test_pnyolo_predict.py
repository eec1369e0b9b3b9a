"""pnyolo-predict writes what other tools read; pnyolo-eval --results scores any detector's results;
TensorBoard curves continue across a resume."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_pnyolo_common import TINY, make_dataset

from pnyolo.cli import eval_main, predict_main, train_main
from tools.exporters.coco import export_coco, read_coco

torch.set_num_threads(2)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("predict")
    ds = make_dataset(tmp / "ds", n_scenarios=3)
    sets = sum((["--set", s] for s in TINY + ["train.max_steps=4", "train.epochs=2", "train.val_every=1"]), [])
    assert train_main([str(ds), "--out", str(tmp / "run"), "--quiet", *sets]) == 0
    export_coco(__import__("dataset_spec").Dataset.open(ds), tmp / "coco", variant="all")
    return tmp


def test_predictions_load_in_pycocotools_against_the_coco_export(trained, capsys):
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    out = trained / "pred"
    assert predict_main([str(trained / "run" / "latest.pt"), str(trained / "ds"), "--split", "test", "--variant", "all",
                         "--conf", "0.001", "--out", str(out), "--pictures", "1"]) == 0
    rows = json.loads((out / "results_test.json").read_text())
    gt = COCO(str(trained / "coco" / "annotations" / "instances_test.json"))
    assert rows and {r["image_id"] for r in rows} <= set(gt.getImgIds())
    assert {r["category_id"] for r in rows} <= set(gt.getCatIds())
    ev = COCOeval(gt, gt.loadRes(str(out / "results_test.json")), "bbox")
    ev.evaluate(), ev.accumulate(), ev.summarize()
    assert 0.0 <= ev.stats[1] <= 1.0  # AP50 of a barely trained detector: any number, but computed
    views = list((out / "views").rglob("*.json"))
    assert len(views) == len(gt.getImgIds())  # one file per image scored
    rec = json.loads(views[0].read_text())
    assert {"scenario", "camera", "lighting", "detections"} <= set(rec)
    assert all(len(d["box"]) == 4 and d["distance_m"] is None or d["distance_m"] > 0 for d in rec["detections"])
    assert list((out / "pictures").glob("*.png"))


def _perfect_results(coco_dir, split):
    doc = read_coco(coco_dir / "annotations" / f"instances_{split}.json")
    return [{"image_id": a["image_id"], "category_id": a["category_id"], "bbox": a["bbox"], "score": 0.9}
            for a in doc["annotations"] if not a["iscrowd"]]


def test_eval_scores_external_results_with_the_project_metrics(trained, tmp_path, capsys):
    perfect = tmp_path / "perfect.json"
    perfect.write_text(json.dumps(_perfect_results(trained / "coco", "test")))
    assert eval_main(["--results", str(perfect), str(trained / "ds"), "--variant", "all", "--out",
                      str(tmp_path / "p")]) == 0
    m = json.loads((tmp_path / "p" / "metrics.json").read_text())
    assert m["strict"]["0.5"]["recall"] == 1.0 and m["strict"]["0.5"]["precision"] == 1.0
    assert m["recall_by_visibility"]["0.4"]["visible 80-100%"]["recall"] == 1.0
    assert "hidden here, seen in another view" in m["recall_by_visibility"]["0.4"]  # the groups of the bench
    empty = tmp_path / "empty.json"
    empty.write_text("[]")
    assert eval_main(["--results", str(empty), str(trained / "ds"), "--variant", "all", "--out", str(tmp_path / "e")]) == 0
    assert json.loads((tmp_path / "e" / "metrics.json").read_text())["strict"]["0.5"]["recall"] == 0.0
    capsys.readouterr()
    wrong = tmp_path / "wrong.json"
    wrong.write_text(json.dumps([{"image_id": 99999, "category_id": 1, "bbox": [0, 0, 5, 5], "score": 0.5}]))
    assert eval_main(["--results", str(wrong), str(trained / "ds"), "--variant", "all"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "image_id 99999" in err and "Traceback" not in err


def test_tensorboard_curves_continue_across_a_resume_without_repeats(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from pnyolo.config import load_config
    from pnyolo.engine.train import train

    ds = make_dataset(tmp_path / "ds", n_scenarios=3)
    run = tmp_path / "run"
    train(ds, load_config(None, TINY + ["train.max_steps=3", "train.epochs=9", "train.val_every=1"]), run, quiet=True)
    train(ds, load_config(None, TINY + ["train.max_steps=5", "train.epochs=9", "train.val_every=1"]), run,
          resume=True, quiet=True)
    acc = EventAccumulator(str(run / "tensorboard"), size_guidance={"images": 0, "scalars": 0})
    acc.Reload()
    # event files are read in name order, which need not be write order within one second
    steps = sorted(e.step for e in acc.Scalars("loss/total"))
    assert steps == [1, 2, 3, 4, 5]  # one curve, no step twice
    assert {"loss/box", "loss/noobj", "train/lr", "train/step_seconds", "val/f1@0.4", "val/ap50"} <= set(acc.Tags()["scalars"])
    assert any(t.startswith("val/recall/") for t in acc.Tags()["scalars"])
    assert acc.Tags()["images"]  # validation pictures with their detections
    assert np.all(np.diff(sorted(e.step for e in acc.Scalars("val/f1@0.4"))) > 0)
