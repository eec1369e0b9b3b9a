"""nuScenes detection results both ways: pnyolo-predict writes results_nusc_SPLIT.json that the devkit's own loader
reads, pnyolo-eval --results scores such a file (ours, or one built from the nuScenes export's annotations, as a
BEVFormer or mmdetection3d run on the export writes it) with the same metrics as a checkpoint, and a wrong field is
named in one line."""
from __future__ import annotations

import json
import re

import pytest
import torch
from test_pnyolo_common import make_dataset, tiny

from pnyolo.cli import eval_main, train_main
from pnyolo.cli.predict import main as predict_main
from tools.projection import label_dataset
from tools.projection_cli import main as labels_main

nuscenes = pytest.importorskip("nuscenes")
from nuscenes.eval.common.loaders import load_prediction  # noqa: E402
from nuscenes.eval.detection.data_classes import DetectionBox  # noqa: E402
from nuscenes.nuscenes import NuScenes  # noqa: E402

from dataset_spec import Dataset  # noqa: E402
from dataset_spec.nuscenes_format import VERSION, detection_name, scene_name  # noqa: E402
from repo_paths import REPO

torch.set_num_threads(2)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("nusc_results")
    ds = make_dataset(tmp / "ds", n_scenarios=3, width=96, height=72, labels=False)
    for path in (ds / "scenarios").glob("*/scenario.json"):  # a bus and a truck: exported as their own categories
        doc = json.loads(path.read_text())
        for actor in doc["actors"]:
            actor["name"] = {"car_b": "bus_b", "car_c": "truck_c"}.get(actor["name"], actor["name"])
        path.write_text(json.dumps(doc))
    label_dataset(ds, progress=False)
    sets = sum((["--set", s] for s in tiny("model.kind=bev", "train.max_steps=3", "train.epochs=1",
                                           "eval.conf_threshold=0.05")), [])
    assert train_main([str(ds), "--out", str(tmp / "run"), "--quiet", *sets]) == 0
    assert labels_main([str(ds), "--no-labelling", "--export", "nuscenes", "--variant", "all", "--out",
                        str(tmp / "exp"), "--quiet"]) == 0
    return tmp


def _annotations_as_results(root, split: str = "test", tracks: bool = False) -> dict:
    """The export's boxes of ``split`` as a detector's results: what a perfect BEVFormer run on it would write
    (``tracks``: a tracker's, each road user's instance its track)."""
    nusc = NuScenes(version=VERSION, dataroot=str(root / "exp" / "nuscenes"), verbose=False)
    scenes = {scene_name(s, v.name) for s in Dataset.open(root / "ds").split(split)
              for v in Dataset.open(root / "ds").scenario(s).lighting}
    results = {s["token"]: [] for s in nusc.sample if nusc.get("scene", s["scene_token"])["name"] in scenes}
    for a in nusc.sample_annotation:
        if a["sample_token"] not in results:
            continue
        name = detection_name(nusc.get("category", nusc.get("instance", a["instance_token"])["category_token"])["name"])
        box = {"sample_token": a["sample_token"], "translation": a["translation"], "size": a["size"],
               "rotation": a["rotation"], "velocity": [0.0, 0.0]}
        box.update({"tracking_name": name, "tracking_score": 1.0, "tracking_id": a["instance_token"]} if tracks else
                   {"detection_name": name, "detection_score": 1.0, "attribute_name": ""})
        results[a["sample_token"]].append(box)
    return {"meta": {"use_camera": True, "use_lidar": False}, "results": results}


def test_the_export_s_own_boxes_score_perfectly_by_the_devkit_s_metrics(run, tmp_path):
    path = tmp_path / "perfect.json"
    path.write_text(json.dumps(_annotations_as_results(run)))
    assert eval_main(["--results", str(path), str(run / "ds"), "--variant", "all", "--out", str(tmp_path / "p"),
                      "--quiet"]) == 0
    names = {b["detection_name"] for boxes in json.loads(path.read_text())["results"].values() for b in boxes}
    assert {"bus", "truck", "car", "pedestrian"} <= names  # read back as the dataset's car and pedestrian
    m = json.loads((tmp_path / "p" / "metrics.json").read_text())
    assert m["strict"]["0.5"]["recall"] == 1.0 and m["strict"]["0.5"]["precision"] == 1.0
    kit = m["3d"]["per_view"]
    assert kit["map"] == pytest.approx(1.0) and kit["errors"]["ATE"] == pytest.approx(0.0, abs=1e-6)
    assert kit["errors"]["ASE"] == pytest.approx(0.0, abs=1e-6) and kit["errors"]["AOE"] == pytest.approx(0.0, abs=1e-6)
    empty = tmp_path / "none.json"
    empty.write_text(json.dumps({"meta": {}, "results": {}}))
    assert eval_main(["--results", str(empty), str(run / "ds"), "--variant", "all", "--out", str(tmp_path / "e"),
                      "--quiet"]) == 0
    assert json.loads((tmp_path / "e" / "metrics.json").read_text())["strict"]["0.5"]["recall"] == 0.0


def test_predict_writes_results_the_devkit_loads_and_eval_scores_them(run, tmp_path):
    out = tmp_path / "pred"
    assert predict_main([str(run / "run" / "latest.pt"), str(run / "ds"), "--variant", "all", "--conf", "0.001",
                         "--out", str(out), "--quiet"]) == 0
    path = out / "results_nusc_test.json"
    boxes, meta = load_prediction(str(path), 500, DetectionBox, verbose=False)  # the devkit's own reader
    doc = json.loads(path.read_text())
    assert set(boxes.sample_tokens) == set(doc["results"]) and meta["use_camera"] is True
    assert all(b.detection_name in ("car", "pedestrian") for b in boxes.all) and len(boxes.all) > 0
    assert set(doc["results"]) == set(_annotations_as_results(run)["results"]), "every test sample, none else"
    assert eval_main(["--results", str(path), str(run / "ds"), "--variant", "all", "--out", str(tmp_path / "r"),
                      "--quiet"]) == 0
    scored = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert scored["3d"]["per_view"]["map"] is not None and 0.0 <= scored["3d"]["per_view"]["nds"] <= 1.0
    counts = scored["strict"]["0.5"]
    assert counts["tp"] + counts["fp"] > 0, "the file's boxes reach the scored views"


@pytest.mark.parametrize("field,value,named", [
    ("translation", [1.0, "x", 0.0], "translation: expected 3 finite numbers"),
    ("size", [1.0, -2.0, 1.5], "size: sizes must be > 0"),
    ("rotation", [0.0, 0.0, 0.0, 0.0], "rotation: not a unit quaternion"),
    ("detection_name", "bicycle", "detection_name: 'bicycle' is not a class"),
    ("detection_score", 1.5, "detection_score: a score in [0, 1]"),
    ("attribute_name", "vehicle.flying", "attribute_name: 'vehicle.flying' is not a nuScenes attribute"),
    ("sample_token", "elsewhere", "is not its sample"),
    ("velocity", None, "no velocity (nuScenes' results format needs it"),  # None: the field left out (issue 83)
    ("attribute_name", None, "no attribute_name (nuScenes' results format needs it"),
])
def test_a_wrong_field_is_named_in_one_line(run, tmp_path, capsys, field, value, named):
    doc = _annotations_as_results(run)
    token = next(t for t, rows in doc["results"].items() if rows)
    doc["results"][token][0][field] = value
    if value is None:
        del doc["results"][token][0][field]
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    capsys.readouterr()
    assert eval_main(["--results", str(path), str(run / "ds"), "--variant", "all", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and named in err and "Traceback" not in err and f"results[{token!r}][0]" in err


def test_a_results_file_without_meta_is_refused_before_the_devkit_sees_it(run, tmp_path, capsys):
    """Rule (issue 83 item 8): what the devkit's load_prediction reads is checked first: no "meta", one line."""
    doc = _annotations_as_results(run)
    del doc["meta"]
    path = tmp_path / "nometa.json"
    path.write_text(json.dumps(doc))
    assert eval_main(["--results", str(path), str(run / "ds"), "--variant", "all", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "the devkit reads both" in err and "KeyError" not in err


def test_a_sample_of_another_split_or_dataset_is_refused(run, tmp_path, capsys):
    path = tmp_path / "other.json"
    path.write_text(json.dumps({"meta": {}, "results": {"0" * 32: []}}))
    assert eval_main(["--results", str(path), str(run / "ds"), "--quiet"]) == 2
    assert "not a sample of" in capsys.readouterr().err
    path.write_text(json.dumps(_annotations_as_results(run, "train")))
    assert eval_main(["--results", str(path), str(run / "ds"), "--variant", "all", "--quiet"]) == 2
    assert "a sample of split train, not test (--split)" in capsys.readouterr().err


def _direct_detection_eval(export, results, tmp_path, classes=("bus", "car", "pedestrian", "truck")):
    """The devkit's DetectionEval called as its README says, on the export and a results file (issue 74)."""
    from nuscenes.eval.detection.config import config_factory
    from nuscenes.eval.detection.evaluate import DetectionEval

    cfg = config_factory("detection_cvpr_2019")
    cfg.class_names = list(classes)  # the classes the export holds (or the two the models name)
    from nuscenes.eval.common.loaders import get_samples_of_custom_split, load_gt_of_sample_tokens

    nusc = NuScenes(version=VERSION, dataroot=str(export), verbose=False)
    tokens = get_samples_of_custom_split("occ_test", nusc)  # the guide's custom-split route to load_gt
    assert tokens and len(load_gt_of_sample_tokens(nusc, tokens, DetectionBox).sample_tokens) == len(tokens)
    metrics, _ = DetectionEval(nusc, cfg, str(results), "occ_test", str(tmp_path / "kit"), verbose=False).evaluate()
    return metrics


def test_the_devkit_detection_eval_figure_is_a_direct_devkit_call(run, tmp_path):
    """pnyolo-eval's DetectionEval figure is the devkit's own DetectionEval on the split's export (one sample per
    frame, its ranges and point filter), called directly on the same export and results: equal."""
    perfect = tmp_path / "perfect.json"
    perfect.write_text(json.dumps(_annotations_as_results(run)))
    assert eval_main(["--results", str(perfect), str(run / "ds"), "--variant", "all", "--out", str(tmp_path / "p"),
                      "--quiet"]) == 0
    kit = json.loads((tmp_path / "p" / "metrics.json").read_text())["devkit_detection_eval"]
    assert kit["map"] == pytest.approx(1.0) and kit["eval_set"] == "occ_test"
    assert eval_main([str(run / "run" / "latest.pt"), str(run / "ds"), "--every-camera", "--conf", "0.01", "--out",
                      str(tmp_path / "m"), "--quiet"]) == 0
    mine = json.loads((tmp_path / "m" / "metrics.json").read_text())["devkit_detection_eval"]
    direct = _direct_detection_eval(run / "exp" / "nuscenes", tmp_path / "m" / mine["results"], tmp_path)
    assert mine["map"] == direct.mean_ap and mine["nds"] == direct.nd_score
    # issue 87: over car and pedestrian, buses and trucks as cars: a direct call with that config on such an export
    named = mine["car_pedestrian"]
    assert named["classes"] == ["car", "pedestrian"] and named["buses_and_trucks"] == "as cars"
    assert labels_main([str(run / "ds"), "--no-labelling", "--export", "nuscenes", "--variant", "all", "--out",
                        str(tmp_path / "named"), "--quiet"]) == 0  # then its bus and truck made cars, as the models
    from dataset_spec.nuscenes_format import VERSION as V
    cats = json.loads((tmp_path / "named" / "nuscenes" / V / "category.json").read_text())
    car = next(c["token"] for c in cats if c["name"] == "vehicle.car")
    inst = json.loads((tmp_path / "named" / "nuscenes" / V / "instance.json").read_text())
    ids = {c["token"] for c in cats if c["name"] in ("vehicle.bus.rigid", "vehicle.truck")}
    assert any(i["category_token"] in ids for i in inst)
    for i in inst:
        i["category_token"] = car if i["category_token"] in ids else i["category_token"]
    (tmp_path / "named" / "nuscenes" / V / "instance.json").write_text(json.dumps(inst))
    by_hand = _direct_detection_eval(tmp_path / "named" / "nuscenes", tmp_path / "m" / mine["results"], tmp_path,
                                     ["car", "pedestrian"])
    assert named["map"] == by_hand.mean_ap and named["nds"] == by_hand.nd_score
    assert set(named["ap_by_distance"]) == {"0.5", "1.0", "2.0", "4.0"} and set(named["errors"]) == {
        "trans_err", "scale_err", "orient_err", "vel_err", "attr_err"}
    assert "The nuScenes devkit's DetectionEval" in (tmp_path / "m" / "metrics.md").read_text()


def test_the_labels_guide_s_devkit_calls_run_as_written(run, tmp_path):
    """The labels guide's block of devkit calls (DetectionEval, TrackingEval, load_gt's custom-split route) runs as
    printed on an export, its placeholders replaced by paths: the export's own boxes and tracks score 1."""
    guide = (REPO / "docs" / "guide" / "labels.md").read_text()
    block = re.search(r"\*\*Splits\.\*\*.*?```python\n(.*?)```", guide, re.S).group(1)
    (tmp_path / "det.json").write_text(json.dumps(_annotations_as_results(run)))
    (tmp_path / "trk.json").write_text(json.dumps(_annotations_as_results(run, tracks=True)))
    for placeholder, path in (("OUT/nuscenes", run / "exp" / "nuscenes"), ("results_nusc_test.json", "det.json"),
                              ("results_tracking.json", "trk.json"), ("out/kit", "kit"), ("out/tk", "tk")):
        assert f'"{placeholder}"' in block
        block = block.replace(f'"{placeholder}"', repr(str(tmp_path / path)))
    names: dict = {}
    exec(compile(block, "labels.md", "exec"), names)  # noqa: S102 - the guide's own code, placeholders replaced
    assert names["metrics"].mean_ap == pytest.approx(1.0)
    assert names["tracking"].serialize()["amota"] == pytest.approx(1.0)
    assert len(names["gt"].sample_tokens) == len(names["tokens"]) > 0


def test_pixelnerf_yolo_writes_3d_results_the_devkit_loads_and_late_fuses_from_the_command_line(run, tmp_path):
    """Issue 89: a pixelNeRF-YOLO checkpoint (with its 3D state, the default) is a model with 3D detections from the
    command line as bev is: pnyolo-predict writes nuScenes results the devkit's own loader reads, and pnyolo-eval
    --late-fusion scores its cars' pooled boxes."""
    from pnyolo.evaluation.evaluate import late_fusion_name

    sets = sum((["--set", s] for s in tiny("train.max_steps=2", "train.epochs=1")), [])
    assert train_main([str(run / "ds"), "--out", str(tmp_path / "pny"), "--quiet", *sets]) == 0
    ckpt = str(tmp_path / "pny" / "latest.pt")
    assert predict_main([ckpt, str(run / "ds"), "--variant", "all", "--conf", "0.001", "--out", str(tmp_path / "p"),
                         "--quiet"]) == 0
    boxes, _ = load_prediction(str(tmp_path / "p" / "results_nusc_test.json"), 500, DetectionBox, verbose=False)
    assert len(boxes.all) > 0 and all(b.size[0] > 0 and b.size[1] > 0 for b in boxes.all)  # sized world boxes
    assert eval_main([ckpt, str(run / "ds"), "--every-camera", "--late-fusion", "--conf", "0.001", "--out",
                      str(tmp_path / "e"), "--quiet"]) == 0
    rows = json.loads((tmp_path / "e" / "comparison.json").read_text())["models"]
    assert late_fusion_name("pixelnerf-yolo") in rows and rows[late_fusion_name("pixelnerf-yolo")]["predictions"] > 0
