"""The detectors on sequences: an item is (scenario, frame, lighting, views); splits stay by layout, so no
frame of a test layout is ever in training; training, evaluation and prediction read every frame."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from test_pnyolo_common import TINY, for_kind

from dataset_spec import Dataset
from dataset_spec.synthetic import write_synthetic_dataset
from pnyolo.cli import eval_main, train_main
from pnyolo.config import load_config
from pnyolo.data.dataset import Delay, MultiViewDataset
from pnyolo.cli.predict import main as predict_main
from tools.exporters.coco import export_coco
from tools.projection import label_dataset

torch.set_num_threads(2)


@pytest.fixture(scope="module")
def sequences(tmp_path_factory):
    root = tmp_path_factory.mktemp("pnseq") / "ds"
    write_synthetic_dataset(root, n_scenarios=3, frames=3, fps=2.0)
    label_dataset(root, progress=False)
    return root


def test_items_are_frames_of_the_split_s_layouts_only(sequences):
    ds, cfg, seen = Dataset.open(sequences), load_config(None, TINY), {}
    for split in ("train", "val", "test"):
        data = MultiViewDataset(sequences, split, cfg, training=split == "train")
        seen[split] = {it.scenario for it in data.items}
        assert seen[split] == set(ds.split(split))
        for s in seen[split]:  # every frame under every lighting
            assert sorted({(it.frame, it.variant) for it in data.items if it.scenario == s}) == \
                [(f, v) for f in range(3) for v in ("dusk", "noon")]
    assert not seen["train"] & (seen["test"] | seen["val"])
    data = MultiViewDataset(sequences, "test", cfg)
    at2 = data.load(data.items[0].scenario, "noon", [0, 1, 2], frame=2)
    at0 = data.load(data.items[0].scenario, "noon", [0, 1, 2], frame=0)
    assert at2.frame == 2 and not torch.equal(at2.images, at0.images)  # the road users moved
    assert not torch.equal(at2.boxes_3d, at0.boxes_3d)
    truth = ds.scenario_at(at2.scenario, 2)
    walker = next(a for a in truth.actors if a.name == "ped_a")
    row = at2.actor_ids.index(walker.id)
    np.testing.assert_allclose(at2.boxes_3d[row, :3].numpy(), walker.box.center, atol=1e-5)


def test_train_eval_and_predict_run_on_sequences(sequences, tmp_path, capsys):
    sets = sum((["--set", s] for s in TINY + ["train.max_steps=3", "train.epochs=1"]), [])
    assert train_main([str(sequences), "--out", str(tmp_path / "run"), "--quiet", *sets]) == 0
    assert eval_main([str(tmp_path / "run" / "latest.pt"), str(sequences), "--split", "test", "--out",
                      str(tmp_path / "eval"), "--quiet"]) == 0
    export_coco(Dataset.open(sequences), tmp_path / "coco", variant="all")
    assert predict_main([str(tmp_path / "run" / "latest.pt"), str(sequences), "--split", "test", "--variant", "all",
                         "--conf", "0.001", "--out", str(tmp_path / "pred"), "--quiet"]) == 0
    views = sorted(p.name for p in (tmp_path / "pred" / "views").rglob("*.json"))
    assert len(views) == 3 * 3 * 2 and "cam_0__f0002__noon.json" in views  # cameras x frames x lightings
    rec = json.loads(next((tmp_path / "pred" / "views").rglob("cam_0__f0002__noon.json")).read_text())
    assert rec["frame"] == 2
    gt = json.loads((tmp_path / "coco" / "annotations" / "instances_test.json").read_text())
    rows = json.loads((tmp_path / "pred" / "results_test.json").read_text())
    assert {r["image_id"] for r in rows} <= {im["id"] for im in gt["images"]}


def test_a_delay_moves_every_source_view_by_whole_frames_and_never_the_target(sequences):
    ds = Dataset.open(sequences)
    cfg = load_config(None, TINY)
    data = MultiViewDataset(sequences, "test", cfg, every_camera=True, delay=Delay(1000.0))  # 2 frames at 2 fps
    assert {it.frame for it in data.items} == {2} and all(it.group == ([0, 1, 2], [0, 1, 2]) for it in data.items)
    assert sorted(it.target for it in data.items if it.variant == "noon") == [0, 1, 2]  # each camera once
    item = data[0]
    scenario, cams = item.scenario, [ds.scenario(item.scenario).cameras[i].name for i in item.views]
    assert item.frame == 2 and item.view_frames == [2, 0, 0] and item.scored == [0] and item.grid_views == [0, 1, 2]
    for k, (name, at) in enumerate(zip(cams, item.view_frames)):
        rgb = torch.from_numpy(ds.read_rgb(scenario, name, item.variant, at)).permute(2, 0, 1).float() / 255
        assert torch.equal(item.images[k], rgb)
    truth = ds.scenario_at(scenario, 2)  # the ground truth is of now
    walker = next(a for a in truth.actors if a.name == "ped_a")
    np.testing.assert_allclose(item.boxes_3d[item.actor_ids.index(walker.id), :3].numpy(), walker.box.center,
                               atol=1e-5)


@pytest.mark.parametrize("delay, words", [(250.0, "nearest values are 0 and 500 ms"),
                                          (1500.0, "no frame that much earlier")])
def test_a_delay_that_is_not_whole_frames_is_refused_naming_the_nearest(sequences, tmp_path, capsys, delay, words):
    sets = sum((["--set", s] for s in TINY + ["train.max_steps=1", "train.epochs=1"]), [])
    assert train_main([str(sequences), "--out", str(tmp_path / "run"), "--quiet", *sets]) == 0
    capsys.readouterr()
    assert eval_main([str(tmp_path / "run" / "latest.pt"), str(sequences), "--every-camera", "--delay-ms", str(delay),
                      "--out", str(tmp_path / "e"), "--quiet"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0]


@pytest.fixture(scope="module")
def bev_run(sequences, tmp_path_factory):
    run = tmp_path_factory.mktemp("bevseq") / "run"
    sets = sum((["--set", s] for s in for_kind(TINY, ["train.max_steps=2", "train.epochs=1", "model.kind=bev"])), [])
    assert train_main([str(sequences), "--out", str(run), "--quiet", *sets]) == 0
    return run / "latest.pt"


def test_a_delay_scores_exactly_what_no_delay_scores_on_the_same_frames(sequences, bev_run, tmp_path, capsys):
    """Issue 63, item 8: the same frames, camera groups, ground truth and ground grid at every delay (bev's grid
    once covered the target camera alone with a delay: 108 target detections instead of 161)."""
    from pnyolo.engine.checkpoint import load_detector, read_checkpoint

    cfg = load_config(None, TINY)
    now = MultiViewDataset(sequences, "test", cfg, every_camera=True, delay=Delay(from_ms=1000.0))
    late = MultiViewDataset(sequences, "test", cfg, every_camera=True, delay=Delay(1000.0))
    model, _ = load_detector(read_checkpoint(bev_run), bev_run, late.class_names, "cpu")
    scored = {}
    for item in (now[k] for k in range(len(now))):
        for v in item.scored:
            scored[(item.scenario, item.frame, item.variant, item.views[v])] = (item.gt[v].boxes, model.grid_for(
                item.K, item.camera_to_world, item.grid.width, item.grid.height, item.grid_views))
    assert len(scored) == len(late)  # each camera of each group scored once, in an item of its own
    for item in (late[k] for k in range(len(late))):
        boxes, grid = scored[(item.scenario, item.frame, item.variant, item.views[item.scored[0]])]
        assert np.array_equal(item.gt[item.scored[0]].boxes, boxes)
        assert model.grid_for(item.K, item.camera_to_world, item.grid.width, item.grid.height, item.grid_views) == grid
    runs = {}
    for name, extra in (("now", ["--delay-ms", "0", "--from-ms", "1000"]), ("late", ["--delay-ms", "1000"])):
        assert eval_main([str(bev_run), str(sequences), "--every-camera", "--conf", "0.01", *extra, "--out",
                          str(tmp_path / name), "--quiet"]) == 0
        runs[name] = json.loads((tmp_path / name / "metrics.json").read_text())
    assert "2 frames less than 1000 ms into their sequences left out" in capsys.readouterr().out  # 1 test sequence
    assert (runs["now"]["views"], runs["now"]["ground_truth"]) == (runs["late"]["views"], runs["late"]["ground_truth"])
    assert runs["now"]["from_ms"] == 1000 and runs["late"]["from_ms"] is None  # the two runs told apart (issue 74)
    assert "from_ms 1000" in (tmp_path / "now" / "metrics.md").read_text().splitlines()[0]


def test_hidden_but_seen_is_what_the_other_views_late_images_show(sequences):
    """With a delay a road user counts as seen in another view by that view's image as the model received it."""
    ds = Dataset.open(sequences)
    late = MultiViewDataset(sequences, "test", load_config(None, TINY), every_camera=True, delay=Delay(1000.0))
    for item in (late[k] for k in range(len(late))):
        v = item.scored[0]
        gt = item.gt[v]
        for row, seen in zip(gt.object_rows, gt.seen_elsewhere):
            aid = item.actor_ids[row]
            pixels = [o.visible_pixels for w, name in enumerate(item.camera_names) if w != v
                      for o in ds.read_labels(item.scenario, name, item.view_frames[w]).objects if o.instance_id == aid]
            assert seen == any(p is None or p > 0 for p in pixels)


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_delay_zero_is_today_s_evaluation_and_a_delay_changes_what_late_fusion_sees(sequences, bev_run, tmp_path):
    ckpt, runs = str(bev_run), {}
    for name, extra in (("plain", []), ("zero", ["--delay-ms", "0"]), ("late", ["--delay-ms", "500"])):
        assert eval_main([ckpt, str(sequences), "--every-camera", "--late-fusion", "--conf", "0.01", *extra,
                          "--out", str(tmp_path / name), "--quiet"]) == 0
        runs[name] = json.loads((tmp_path / name / "comparison.json").read_text())
    assert runs["plain"]["models"] == runs["zero"]["models"]  # every figure
    assert runs["late"]["delay_ms"] == 500.0
    late, plain = runs["late"]["models"], runs["plain"]["models"]
    assert late["bev, late fusion"] != plain["bev, late fusion"] and late["bev"] != plain["bev"]


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_pnyolo_eval_into_an_ego_keeps_the_ego_s_detections_and_adds_the_other_cars(sequences, bev_run, tmp_path):
    """``pnyolo-eval --late-fusion --into EGO``: a row beside the two models'; when no car sends it is the ego
    alone, figure for figure; when they send it keeps every ego detection and adds some."""
    ckpt, rows = str(bev_run), {}
    for name, conf in (("silent", "1.0"), ("sending", "0.02")):
        assert eval_main([ckpt, str(sequences), "--every-camera", "--late-fusion", "--into", ckpt, "--ego-conf", "0.02",
                          "--conf", conf, "--out", str(tmp_path / name), "--quiet"]) == 0
        rows[name] = json.loads((tmp_path / name / "comparison.json").read_text())["models"]
    into = "bev (A), late fusion into bev (B)"
    assert set(rows["silent"]) == {"bev (A)", "bev (B)", "bev (A), late fusion", into}
    assert rows["silent"][into]["strict"] == rows["silent"]["bev (B)"]["strict"]
    assert rows["silent"][into]["predictions"] == rows["silent"]["bev (B)"]["predictions"] > 0
    ego, sending = rows["sending"]["bev (B)"], rows["sending"][into]
    assert ego == rows["silent"]["bev (B)"] and sending["predictions"] > ego["predictions"]
    assert all(sending["strict"][t]["tp"] >= ego["strict"][t]["tp"] for t in ego["strict"])


def test_pnyolo_track_writes_mot_rows_and_motmetrics_figures(sequences, bev_run, tmp_path, capsys):
    pytest.importorskip("motmetrics")
    from pnyolo.cli.track import main as track_main

    for extra in ([], ["--late-fusion"]):
        out = tmp_path / ("late" if extra else "rig")
        extra = extra + ["--conf", "0.002"] if extra else extra  # late fusion: what the cars send
        assert track_main([str(bev_run), str(sequences), "--start", "0.002", "--keep", "0.001", "--min-hits", "1",
                           *extra, "--out", str(out), "--quiet"]) == 0
        metrics = json.loads((out / "metrics.json").read_text())["metrics"]
        test = Dataset.open(sequences).split("test")
        assert set(metrics) == {f"{s}__noon" for s in test} | {"OVERALL"}  # each scenario's first lighting
        overall = metrics["OVERALL"]
        assert overall["num_objects"] > 0 and overall["mota"] <= 1.0 and 0 <= overall["idf1"] <= 1.0
        rows = [line.split(",") for line in next((out / "tracks").glob("*.txt")).read_text().splitlines()]
        assert rows and all(len(r) == 10 and 1 <= int(r[0]) <= 3 and r[2:6] == ["-1"] * 4 for r in rows)
        _rescored_from_the_files(out, sequences, metrics)
    assert "MOTA" in capsys.readouterr().out
    assert track_main([str(bev_run), str(sequences), "--gate", "0", "--out", str(tmp_path / "x")]) != 0
    assert track_main([str(bev_run), str(sequences), "--choose-on", "val", "--out", str(tmp_path / "c"),
                       "--quiet"]) == 0  # the validation sequences choose the point (issue 88)
    chosen = json.loads((tmp_path / "c" / "metrics.json").read_text())
    from pnyolo.engine.checkpoint import read_checkpoint

    conf = read_checkpoint(bev_run)["config"]["eval"]["conf_threshold"]  # the grid's starts, the detector's own
    assert chosen["chosen_on"] == "val" and chosen["tracker_point"]["start"] in (0.6, 0.4, conf)
    _tracking_eval_is_a_direct_devkit_call(tmp_path / "rig", sequences, tmp_path)


def _tracking_eval_is_a_direct_devkit_call(out, sequences, tmp_path):
    """pnyolo-track's TrackingEval figure is the devkit's own TrackingEval called on an export of the split (each
    scenario's first lighting, as tracked) with the written results (issue 74)."""
    pytest.importorskip("nuscenes")
    from nuscenes.eval.common.config import config_factory
    from nuscenes.eval.tracking.evaluate import TrackingEval

    from dataset_spec.nuscenes_format import VERSION
    from tools.projection_cli import main as labels_main

    kit = json.loads((out / "metrics.json").read_text())["devkit_tracking_eval"]
    assert labels_main([str(sequences), "--no-labelling", "--export", "nuscenes", "--out", str(tmp_path / "exp"),
                        "--quiet"]) == 0
    cfg = config_factory("tracking_nips_2019")
    cfg.class_names = cfg.tracking_names = [c for c in cfg.tracking_names if c in ("bus", "car", "pedestrian", "truck")]
    metrics, _ = TrackingEval(cfg, str(out / kit["results"]), "occ_test", str(tmp_path / "tk"), VERSION,
                              str(tmp_path / "exp" / "nuscenes"), verbose=False).evaluate()
    direct = metrics.serialize()["amota"]
    assert kit["amota"] == (None if direct != direct else direct) and kit["eval_set"] == "occ_test"


def _rescored_from_the_files(out, sequences, metrics):
    """Anyone's recomputation from the written track files (motmetrics at 1 m) agrees with metrics.json to 1e-9."""
    from pnyolo.tracking.scoring import ground_truth_tracks, score_tracks
    from pnyolo.decoding.ground_tracker import TrackRow

    ds = Dataset.open(sequences)
    again = {}
    for path in (out / "tracks").glob("*.txt"):
        scenario = path.stem.split("__")[0]
        rows = [TrackRow(int(r[0]) - 1, int(r[1]), 0, float(r[7]), float(r[8]), 0.0, 0.0, float(r[6]))
                for r in (line.split(",") for line in path.read_text().splitlines())]
        again[path.stem] = (ground_truth_tracks(ds, scenario, ds.info.detectable_classes), rows)
    figures = score_tracks(again)
    for name, got in metrics.items():
        for key in ("mota", "motp", "idf1"):
            assert (got[key] is None and figures[name][key] is None) or abs(got[key] - figures[name][key]) <= 1e-9


def _scoring(model, cfg, dataset, own: bool = True):
    from pnyolo.bench.plan import predict_scoring
    from pnyolo.engine.predict import Trained

    return predict_scoring(Trained(None, model, cfg), dataset, own=own)


def test_a_late_car_s_message_carries_its_own_tracker_s_velocities_from_the_same_predictions(sequences, bev_run):
    """Issue 77, item 3: a late message's velocities come from its sender's own tracker over the very detections
    it sends (the cars' own-view predictions of every frame), and late fusion moves it to now by them."""
    from pnyolo.cooperation.late_fusion import LateRule, late_fusion
    from pnyolo.cooperation.senders import OwnViews, sent_key
    from pnyolo.decoding.ground_tracker import EVERY_DETECTION, GroundTracker
    from pnyolo.engine.checkpoint import load_detector, read_checkpoint
    from pnyolo.engine.predict import Condition, predict

    ckpt = read_checkpoint(bev_run)
    cfg0 = load_config(None, TINY)
    data = MultiViewDataset(sequences, "test", cfg0, every_camera=True, delay=Delay(500.0))
    whole = MultiViewDataset(sequences, "test", cfg0, every_camera=True)
    model, cfg = load_detector(ckpt, bev_run, data.class_names, "cpu")
    cars = OwnViews(predict(model, whole, cfg.eval, Condition(own_view=True)), cfg.eval)
    item = next(data[k] for k in range(len(data)) if data.items[k].frame == 2)  # its source views of frame 1
    messages = cars.messages(item, 0.01)
    for b, m in enumerate(messages):
        camera, frame = item.views[b], item.view_frames[b]
        assert m.detections is cars.detections(sent_key(item, camera, frame), 0.01)
        assert m.timestamp == frame / item.fps
        if frame == item.frame or not len(m.detections):
            assert m.velocities is None  # on time: nothing to move
            continue
        tracker = GroundTracker(item.fps, EVERY_DETECTION)  # the sender's own tracker over what it sent, frame by frame
        for f in range(frame + 1):
            steps = tracker.step(f, cars.detections(sent_key(item, camera, f), 0.01))
        assert np.allclose(m.velocities, [s[2:] for s, _ in steps])
        moved = m.at(item.frame / item.fps).detections
        assert np.allclose(moved.boxes[:, :2], m.detections.boxes[:, :2] + m.velocities * 0.5)
    assert any(m.velocities is not None for m in messages)
    rule = LateRule.of(cfg.eval, 0.01)
    assert [len(d.scores) for d in late_fusion(messages, item, rule)] == \
        [len(d.scores) for d in late_fusion([m.at(item.frame / item.fps) for m in messages], item, rule)]


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_on_a_frozen_sequence_a_delay_changes_nothing_late_fusion_included(bev_run, tmp_path, monkeypatch):
    """Issue 77, item 3: every frame the same (true speed 0), the other cars' views 1000 ms old score exactly what
    the same frames without a delay score, late fusion too (its messages and their velocities are the cars' own)."""
    import dataset_spec.synthetic as synthetic

    monkeypatch.setattr(synthetic, "SYNTHETIC_VELOCITIES", {})
    frozen = write_synthetic_dataset(tmp_path / "frozen", n_scenarios=3, frames=3, fps=2.0)
    label_dataset(frozen, progress=False)
    runs = {}
    for name, extra in (("now", ["--delay-ms", "0", "--from-ms", "1000"]), ("late", ["--delay-ms", "1000"])):
        assert eval_main([str(bev_run), str(frozen), "--every-camera", "--late-fusion", "--conf", "0.01", *extra,
                          "--out", str(tmp_path / name), "--quiet"]) == 0
        runs[name] = json.loads((tmp_path / name / "comparison.json").read_text())
    assert set(runs["now"]["models"]) == {"bev", "bev, late fusion"}
    assert runs["now"]["models"] == runs["late"]["models"]  # every figure


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_late_fusion_by_agreement_keeps_the_best_car_s_road_users_and_its_choice_reproduces_on_validation(
        sequences, bev_run):
    """Kept from the send threshold, agreement keeps exactly the road users (and boxes) of the best-car rule,
    each scored at least as high; the rule chosen on validation scores there what its sweep said. Late fusion
    reads messages alone (issue 77)."""
    import dataclasses

    from pnyolo.bench.late_choice import choose_late_fusion
    from pnyolo.bench.presets import load_preset
    from pnyolo.cooperation.late_fusion import LateRule, late_fusion
    from pnyolo.engine.checkpoint import load_detector, read_checkpoint
    from pnyolo.evaluation.evaluate import Comparison, Entry, LATE_FUSION, evaluate_models

    ckpt = read_checkpoint(bev_run)
    test = MultiViewDataset(sequences, "test", load_config(None, TINY), every_camera=True)
    model, cfg = load_detector(ckpt, bev_run, test.class_names, "cpu")
    cfg = replace(cfg, eval=replace(cfg.eval, conf_threshold=0.02))
    cars = _scoring(model, cfg, test).cars
    item = cars.preds.items[0].item
    messages = cars.messages(item, 0.02)
    best_car = late_fusion(messages, item, LateRule.of(cfg.eval))
    agreed = late_fusion(messages, item, LateRule(0.02, 0.02, None, cfg.eval.centre_nms_m))
    assert sum(len(v.scores) for v in best_car) > 0
    for a, b in zip(best_car, agreed):
        order_a, order_b = np.lexsort(a.boxes.T), np.lexsort(b.boxes.T)
        assert np.allclose(a.boxes[order_a], b.boxes[order_b]) and (b.scores[order_b] >= a.scores[order_a] - 1e-12).all()
    assert all(len(v.scores) == 0 for v in late_fusion(messages, item, LateRule(0.02, 1.0, None, cfg.eval.centre_nms_m)))

    val = MultiViewDataset(sequences, "val", load_config(None, TINY), every_camera=True, training=False)
    preset = dataclasses.replace(load_preset("smoke"), conf_grid=(0.01, 0.03, 0.1, 0.3))
    scoring = _scoring(model, cfg, val)
    choice = choose_late_fusion(preset, scoring.cars, cfg)
    assert choice.rule in ("best car", "agreement", "calibrated agreement") and choice.val_f1 >= choice.best_car_val_f1
    point = choice.point(cfg.eval)  # a new operating point; the model's own is untouched (issue 86)
    assert (point.late_keep is None) == (choice.rule == "best car") and point.late_send == choice.send
    assert point.late_calibration == choice.calibration and cfg.eval.late_send is None
    scoring = replace(scoring, config=replace(cfg, eval=point))
    accs = evaluate_models(Comparison({"bev": scoring}, late=("bev",)), val)
    assert accs[Entry("bev", LATE_FUSION)].summary()["strict"][preset.iou]["f1"] == pytest.approx(choice.val_f1)


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_late_fusion_into_an_ego_keeps_its_own_view_and_adds_only_the_other_cars(sequences, bev_run):
    """Into an ego, a target view keeps the ego's detections above its threshold and gains the other cars'
    pooled reports, never its own car's; the thresholds chosen on validation score there what the choice said."""
    import dataclasses

    from pnyolo.bench.late_choice import choose_late_into
    from pnyolo.bench.presets import load_preset
    from pnyolo.cooperation.late_fusion import Ego, LateRule, car_id, late_fusion, pool_cars
    from pnyolo.cooperation.pose_noise import car_of
    from pnyolo.decoding.world import project_into_views
    from pnyolo.engine.checkpoint import load_detector, read_checkpoint
    from pnyolo.evaluation.evaluate import Comparison, Entry, LATE_FUSION, LateInto, evaluate_models

    ckpt = read_checkpoint(bev_run)
    test = MultiViewDataset(sequences, "test", load_config(None, TINY), every_camera=True)
    model, cfg = load_detector(ckpt, bev_run, test.class_names, "cpu")
    cfg = replace(cfg, eval=replace(cfg.eval, conf_threshold=0.02))
    scoring = _scoring(model, cfg, test)
    item, ego_dets = scoring.clean.items[0].item, scoring.clean.detections_at(0, cfg.eval)
    assert sum(len(d.scores) for d in ego_dets) > 0
    alone = late_fusion(scoring.cars.messages(item, 1.01), item, LateRule.of(cfg.eval, 1.01),
                        ego=Ego(ego_dets, 0.05, 0.5))  # nobody else sends
    for v in item.scored:
        kept = ego_dets[v].above(0.05)
        assert sorted(map(tuple, alone[v].boxes.round(6))) == sorted(map(tuple, kept.boxes.round(6)))
    nothing = [d.above(2.0) for d in ego_dets]
    others = late_fusion(scoring.cars.messages(item, 0.02), item, LateRule.of(cfg.eval, 0.02),
                         ego=Ego(nothing, 0.05, 0.5))
    cars = scoring.own.world_at(0, cfg.eval, 0.02)
    for v in item.scored:
        rest = [b for b in range(len(cars)) if car_of(item, b) != car_of(item, v)]
        pooled = pool_cars([cars[b] for b in rest], [car_id(item, b) for b in rest], cfg.eval.centre_nms_m)
        want = project_into_views(pooled, item, [v])[v]
        assert sorted(want.scores.round(9)) == sorted(others[v].scores.round(9))

    val = MultiViewDataset(sequences, "val", load_config(None, TINY), every_camera=True, training=False)
    preset = dataclasses.replace(load_preset("smoke"), conf_grid=(0.01, 0.03, 0.1))
    on_val = _scoring(model, cfg, val)
    choice = choose_late_into(preset, on_val.cars, cfg, on_val.clean, cfg, "ego")
    assert len(choice.val_grid) == 6 and choice.val_f1 == max(r["f1"] for r in choice.val_grid)  # ego from 0.03
    assert {r["ego_threshold"] for r in choice.val_grid} == {0.03, 0.1}  # never below the ego's own threshold
    plan = Comparison({"bev": on_val, "ego": on_val}, late_into=LateInto("bev", "ego", choice.send, choice.ego_threshold))
    accs = evaluate_models(plan, val)
    assert Entry("bev", LATE_FUSION, "ego").name == "bev, late fusion into ego"
    assert accs[Entry("bev", LATE_FUSION, "ego")].summary()["strict"][preset.iou]["f1"] == pytest.approx(choice.val_f1)
