"""pnyolo-predict writes what other tools read; pnyolo-eval --results scores any detector's results;
TensorBoard curves continue across a resume."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_pnyolo_common import TINY, make_dataset

from pnyolo.cli import eval_main, train_main
from pnyolo.cli.predict import main as predict_main
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
    from pnyolo.training.train import train

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


def _ultralytics_rows(trained, split, base=1):
    """What Ultralytics' model.val(save_json=True) writes for a perfect detector on the YOLO export:
    image_id the file stem, category_id the class index (+1 since Ultralytics 8.1), bbox [x, y, w, h]."""
    from dataset_spec import Dataset
    from tools.exporters.common import export_views

    ds = Dataset.open(trained / "ds")
    index = {n: k for k, n in enumerate(ds.info.detectable_classes)}
    return [{"image_id": v.stem, "category_id": index[o.cls] + base, "score": 0.8,
             "bbox": [float(o.box[0]) + 0.5, float(o.box[1]) + 0.5, float(o.box[2] - o.box[0]),
                      float(o.box[3] - o.box[1])]}
            for v in export_views(ds, None, None, "all") if v.split == split for o in v.labels if o.cls in index]


@pytest.mark.parametrize("base", [1, 0])
def test_eval_reads_ultralytics_predictions_as_they_come(trained, tmp_path, capsys, base):
    rows = _ultralytics_rows(trained, "test", base)
    assert rows and all(isinstance(r["image_id"], str) for r in rows)
    if base == 0:
        assert any(r["category_id"] == 0 for r in rows)  # what tells an older Ultralytics' numbering
    path = tmp_path / "predictions.json"
    path.write_text(json.dumps(rows))
    assert eval_main(["--results", str(path), str(trained / "ds"), "--variant", "all", "--out", str(tmp_path / "u"),
                      "--quiet"]) == 0
    m = json.loads((tmp_path / "u" / "metrics.json").read_text())
    assert m["strict"]["0.5"]["recall"] == 1.0 and m["strict"]["0.5"]["precision"] == 1.0


def test_results_of_one_split_given_for_another_are_refused(trained, tmp_path, capsys):
    from dataset_spec import Dataset
    from pnyolo.evaluation.predictions import image_index

    ds = Dataset.open(trained / "ds")
    refs = list(image_index(ds, "all").values())
    assert len({r.id for r in refs}) == len(refs)  # COCO ids are unique across splits
    assert {r.split for r in refs} >= {"train", "test"}
    for name, rows in (("coco", _perfect_results(trained / "coco", "test")),
                       ("ultralytics", _ultralytics_rows(trained, "test"))):
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps(rows))
        assert eval_main(["--results", str(path), str(trained / "ds"), "--variant", "all", "--split", "train"]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and "no image of split train (it is in split test)" in err, err


def test_ap50_agrees_with_cocoeval_with_crowd_regions():
    """The project's AP50 against pycocotools' COCOeval on the same ground truth (excluded road users
    as iscrowd regions) and detections (fewer than COCOeval's 100 per image)."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    from pnyolo.evaluation.metrics import ViewDetections, ViewGroundTruth, average_precision
    from tools.exporters.coco import box_from_coco

    rng = np.random.default_rng(7)
    images, anns, dets, records = [], [], [], []
    for image_id in range(1, 21):
        images.append({"id": image_id, "width": 320, "height": 180})
        gt_boxes, gt_cls, ex_boxes, ex_cls = [], [], [], []
        for crowd in [0] * int(rng.integers(0, 6)) + [1] * int(rng.integers(0, 4)):
            w, h = rng.uniform(4, 60, 2)
            bbox = [float(rng.uniform(0, 320 - w)), float(rng.uniform(0, 180 - h)), float(w), float(h)]
            cat = int(rng.integers(1, 3))
            anns.append({"id": len(anns) + 1, "image_id": image_id, "category_id": cat, "bbox": bbox,
                         "area": float(w * h), "iscrowd": crowd})
            (ex_boxes if crowd else gt_boxes).append(box_from_coco(bbox))
            (ex_cls if crowd else gt_cls).append(cat - 1)
        rows = []
        for a in [a for a in anns if a["image_id"] == image_id]:
            for _ in range(int(rng.integers(0, 3))):  # hits, near misses and duplicates, on crowds too
                x, y, w, h = a["bbox"]
                jitter = rng.normal(0, 0.15, 4) * [w, h, w, h]
                cat = a["category_id"] if rng.random() < 0.85 else 3 - a["category_id"]
                rows.append([x + jitter[0], y + jitter[1], max(1.0, w + jitter[2]), max(1.0, h + jitter[3]), cat])
        for _ in range(int(rng.integers(0, 4))):  # detections on nothing
            w, h = rng.uniform(4, 40, 2)
            rows.append([rng.uniform(0, 300), rng.uniform(0, 160), w, h, int(rng.integers(1, 3))])
        scores = rng.uniform(0.05, 1.0, len(rows))
        for (x, y, w, h, cat), score in zip(rows, scores):
            dets.append({"image_id": image_id, "category_id": int(cat), "bbox": [float(x), float(y), float(w), float(h)],
                         "score": float(score)})
        records.append((ViewDetections(np.array([box_from_coco(r[:4]) for r in rows]).reshape(-1, 4), scores,
                                       np.array([int(r[4]) - 1 for r in rows], dtype=np.int64)),
                        ViewGroundTruth(np.array(gt_boxes).reshape(-1, 4), np.array(gt_cls, dtype=np.int64),
                                        excluded_boxes=np.array(ex_boxes).reshape(-1, 4),
                                        excluded_classes=np.array(ex_cls, dtype=np.int64))))
    gt = COCO()
    gt.dataset = {"images": images, "annotations": anns,
                  "categories": [{"id": 1, "name": "car"}, {"id": 2, "name": "pedestrian"}]}
    gt.createIndex()
    ev = COCOeval(gt, gt.loadRes(dets), "bbox")
    ev.evaluate(), ev.accumulate(), ev.summarize()
    assert sum(a["iscrowd"] for a in anns) > 5 and len(dets) > 50
    assert average_precision(records, 0.5, 2) == pytest.approx(ev.stats[1], abs=1e-3)


def test_training_without_validation_says_so_and_leaves_best(tmp_path, capsys):
    from pnyolo.config import load_config
    from pnyolo.engine.runtime import choose_threads
    from pnyolo.training.train import train

    ds = make_dataset(tmp_path / "ds", n_scenarios=2)
    summary = train(ds, load_config(None, TINY + ["train.max_steps=2", "train.epochs=1", "train.threads=0"]),
                    tmp_path / "run")
    first = capsys.readouterr().err.strip().splitlines()[0]
    assert first.startswith("pnyolo-train: ") and "torch thread" in first and "no validation" in first, first
    assert (tmp_path / "run" / "best.pt").is_file()
    cores = len(__import__("os").sched_getaffinity(0))
    assert summary["threads"] == cores  # train.threads 0: every usable core, however busy they are
    assert choose_threads(1) == (1, "train.threads")
    assert choose_threads(cores + 510)[0] == cores and "more than the" in capsys.readouterr().err  # capped, said
    train(ds, load_config(None, TINY + ["train.max_steps=1", "train.epochs=1"]), tmp_path / "quiet", quiet=True)
    said = capsys.readouterr().err.strip().splitlines()
    assert len(said) == 1 and "no validation" in said[0] and "torch thread" not in said[0], said
    n, why = choose_threads(0, processes=64)
    assert n == max(1, cores // 64) and why == f"train.threads 0: the {cores} usable cores"


def test_results_made_on_one_lighting_are_read_by_their_images_under_every_lighting(trained, tmp_path, capsys):
    """Issue 83 item 8: an image id names one image whichever variants an export holds, so results made on the
    default export (the first lighting) scored with --variant all name the same images, and the evaluation says
    that the other lightings' images have no detections; results of every lighting scored on the first alone name
    the lighting to give."""
    from dataset_spec import Dataset
    from pnyolo.evaluation.predictions import image_index

    ds = Dataset.open(trained / "ds")
    first, every = image_index(ds, None), image_index(ds, "all")
    assert all(every[key].id == ref.id for key, ref in first.items())  # the same image, the same id
    out = tmp_path / "pred"
    assert predict_main([str(trained / "run" / "latest.pt"), str(trained / "ds"), "--split", "test", "--conf",
                         "0.001", "--out", str(out), "--quiet"]) == 0
    capsys.readouterr()
    assert eval_main(["--results", str(out / "results_test.json"), str(trained / "ds"), "--variant", "all",
                      "--out", str(tmp_path / "e"), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "names images of lighting variant(s)" in err and "scored with no detections" in err
    assert predict_main([str(trained / "run" / "latest.pt"), str(trained / "ds"), "--split", "test", "--conf",
                         "0.001", "--variant", "all", "--out", str(tmp_path / "all"), "--quiet"]) == 0
    capsys.readouterr()
    assert eval_main(["--results", str(tmp_path / "all" / "results_test.json"), str(trained / "ds"),
                      "--out", str(tmp_path / "e2"), "--quiet"]) == 2
    assert "give --variant all" in capsys.readouterr().err
