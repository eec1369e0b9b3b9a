"""The occlusion benchmark's smoke preset runs end to end: render -> labels -> train both -> evaluate -> report."""
from __future__ import annotations

import json

import pytest
import yaml

pytest.importorskip("bpy")

from dataset_spec import Dataset  # noqa: E402
from dataset_spec.validate import validate  # noqa: E402
from pnyolo.bench.cli import main  # noqa: E402
from pnyolo.bench.presets import load_preset  # noqa: E402
from pnyolo.evaluation.devkit_eval import available as devkit_available  # noqa: E402
from pnyolo.evaluation.evaluate import late_fusion_name, late_into_name, own_view_name  # noqa: E402
from repo_paths import REPO
from report_text import bare_differences  # noqa: E402

MULTI, SINGLE, BEV = "pixelnerf-yolo", "single-view", "bev"  # the smoke preset's kinds (primary, baseline, ...)


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    """The smoke preset run once (with one per-model override): its folder, arguments and report.json."""
    out = tmp_path_factory.mktemp("smoke") / "bench"
    args = ["smoke", "--out", str(out), "--quiet", "--set-model", f"{MULTI}:model.loss.hidden_weight=2"]
    assert main(args) == 0
    return out, args, json.loads((out / "report" / "report.json").read_text())


@pytest.mark.blender
@pytest.mark.slow
def test_smoke_benchmark_end_to_end(smoke):
    out, args, result = smoke
    report = out / "report"
    assert set(result["models"]) == {MULTI, SINGLE, BEV, "fusion", own_view_name(MULTI), own_view_name(BEV),
                                     late_fusion_name(MULTI), late_fusion_name(BEV),  # both place 3D boxes
                                     late_into_name(BEV, SINGLE)}  # the preset's late_sender
    into = result["models"][late_into_name(BEV, SINGLE)]["late_fusion_selection"]  # into the baseline's own view
    assert into["ego"] == SINGLE and into["val_f1"] == max(r["f1"] for r in into["val_grid"])
    assert result["models"][BEV]["3d"] is not None and result["models"][SINGLE]["3d"] is None
    late = result["models"][late_fusion_name(BEV)]
    assert late["feature_bytes_per_car_frame"] > late["bytes_per_car_frame"] >= 0
    rule = late["late_fusion_selection"]  # chosen on validation: agreement only where it beat the best car there
    assert rule["rule"] in ("best car", "agreement", "calibrated agreement") and rule["val_f1"] >= rule["best_car_val_f1"]
    assert (rule["rule"] != "best car") == (rule["val_f1"] > rule["best_car_val_f1"])
    assert (rule["calibration"] is None) == (rule["rule"] != "calibrated agreement")
    assert all(result["models"][k]["inference_ms"] > 0 for k in (MULTI, SINGLE, BEV))
    own, full = result["models"][own_view_name(MULTI)], result["models"][MULTI]
    assert own["ground_truth"] == full["ground_truth"] and own["views"] == full["views"]  # same items, same views
    assert result["dataset"]["test"]["scenarios"] == ["intersection_03", "procedural-20000"]  # built-in, new layout
    train = result["dataset"]["train"]
    assert train["scenarios"] == ["intersection_01", "intersection_01-s1"]  # a layout and its redraw
    ds = Dataset.open(out / "dataset")
    base, redrawn = (ds.scenario(s) for s in train["scenarios"])
    assert redrawn.extras["seed"] == base.extras["seed"] + 1
    from blender_tools.hdri import drawn_variant

    for scn in (base, redrawn):  # --hdr random:noon,dusk: each training scene under its one drawn lighting
        assert [v.name for v in scn.lighting] == [drawn_variant(["noon", "dusk"], scn.name, 0)]
    assert train["render_data_s"] > 0 and train["render_rgb_s"] > 0 and train["bytes"] > 0  # what the data cost
    assert [a.box.to_dict() for a in redrawn.actors] != [a.box.to_dict() for a in base.actors]
    assert result["single_view_ceiling"]["n"] == result["models"][MULTI]["ground_truth"] > 0
    assert 0.0 <= result["single_view_ceiling"]["recall_ceiling"] <= 1.0
    assert all(v is not None for k, v in result["timings"].items())
    for name in ("report.md", "f1_vs_match_iou.png", "recall_by_visibility.png", "comparison.md"):
        assert (report / name).stat().st_size > 0
    text = (report / "report.md").read_text()
    assert "Single-view ceiling" in text and "## Targets" in text and "pnyolo-bench smoke" in text
    assert all(f"- `{k}`: " in text for k in (MULTI, SINGLE, BEV))  # each model described by its kind
    point = result["hidden_target_point"]  # chosen on the multi-view validation sweep, reported beside the targets
    assert "Operating point for the hidden-recall target" in text and point["target"] == 0.5
    assert point["threshold"] in (None, 0.01, 0.45)
    assert f"F1@0.2 {own['strict']['0.2']['f1']:.3f} against {full['strict']['0.2']['f1']:.3f}" in text
    # per-model overrides, that model only: the preset's, then the command line's
    assert (f"{MULTI} only: --set model.sampler.near=2.0 --set model.sampler.far=42.0 --set model.sampler.num_samples=8 "
            "--set model.sampler.slab_clip=true --set model.sampler.height_cap=3.5 --set model.loss.depth=0.1 "
            "--set model.sampler.fine_samples=4 --set model.loss.occupancy=1.0 --set model.loss.hidden_weight=2") in text
    assert result["models"][MULTI]["selection"]["depth_peaks"] in (1, 2)  # chosen on validation
    assert "Sampling coverage" in text and "coverage of hidden-but-seen" in text
    assert "On the ground plane" in text and "Late fusion" in text and "inference per frame" in text
    sweep = result["models"][late_fusion_name(BEV)]["pose_noise_sweep"]  # the pose-noise sweep, sigma 0 and 0.4
    assert set(sweep) == {"0", "0.4"} and sweep["0"]["f1"] == late["strict"]["0.2"]["f1"]
    assert result["models"][SINGLE]["pose_noise_sweep"]["0.4"] == result["models"][SINGLE]["pose_noise_sweep"]["0"]
    assert "When the other cars' poses are wrong" in text and (report / "robustness.png").stat().st_size > 0
    assert all(f in text for f in result["target_figures"].values())  # every target with its figures
    assert "render: data passes / RGB (s)" in text and "against chance" in text  # issue 67: the trade, the floor
    chance = json.loads((report / "comparison.json").read_text())["hidden_seen_against_chance"]
    hidden = result["models"][SINGLE]["recall_by_visibility"]["0.2"]["hidden here, seen in another view"]["recall"]
    assert SINGLE not in chance and chance[MULTI]["chance"] == hidden  # the single view's recall on the same objects
    assert any(k.endswith("hidden-but-seen recall@0.2 >= the single view's on the same objects + 0.1")
               for k in result["targets"])
    loss = {k: yaml.safe_load((out / "runs" / k / "config.yaml").read_text())["model"]["loss"] for k in (MULTI, SINGLE)}
    assert {k: (v["hidden_weight"], v["depth"]) for k, v in loss.items()} == {MULTI: (2.0, 0.1), SINGLE: (1.0, 0.0)}
    assert not [p for p in validate(out / "dataset") if p.severity == "error"]
    for kind in (MULTI, SINGLE, BEV):
        steps = [json.loads(l) for l in (out / "runs" / kind / "log.jsonl").read_text().splitlines()]
        assert max(r.get("step", 0) for r in steps) == 6
    if devkit_available():  # the files the devkit's evaluations scored are kept beside the figures they gave
        for kind in (BEV, MULTI):  # pixelNeRF-YOLO's 3D boxes too (issue 89)
            detection = result["models"][kind]["devkit_detection_eval"]
            assert detection["results"] == "results_nusc_test.json" and detection["map"] is not None
        for name in (BEV, late_fusion_name(BEV), MULTI, late_fusion_name(MULTI)):
            kit = result["models"][name]["tracking"]["devkit_tracking_eval"]
            doc = json.loads((report / name / kit["results"]).read_text())
            assert kit["results"] == "results_nusc_tracking_test.json" and doc["results"] and kit["amota"] is not None
            assert kit["car_pedestrian"]["amota"] is not None  # TrackingEval over the classes the models name too
        # the preset's targets on the 3D state and the tracks (issues 87, 88), judged for the model with 3D detections
        assert {k for k in result["targets"] if k.startswith(f"{BEV}: ")} >= {
            f"{BEV}: DetectionEval NDS (car, pedestrian) >= 0.4", f"{BEV}: MOTA of its tracks >= 0",
            f"{BEV}: TrackingEval AMOTA (car, pedestrian) >= 0.1", f"{BEV}: DetectionEval mATE, m (car, pedestrian) <= 1"}
        assert (report / BEV / "results_nusc_test.json").stat().st_size > 0


@pytest.mark.blender
@pytest.mark.slow
def test_a_rerun_reuses_the_models_and_scores_another_detector_beside_them(smoke, tmp_path, capsys):
    """A re-run reuses the dataset and the trained models; another detector's results are scored beside
    them (here the test split's own ground truth as COCO results: a perfect detector)."""
    from tools.exporters.coco import export_coco, read_coco

    out, args, result = smoke
    report, ds = out / "report", Dataset.open(out / "dataset")
    text = (report / "report.md").read_text()

    export_coco(ds, tmp_path / "coco", variant="all")
    doc = read_coco(tmp_path / "coco" / "annotations" / "instances_test.json")
    perfect = [{"image_id": a["image_id"], "category_id": a["category_id"], "bbox": a["bbox"], "score": 1.0}
               for a in doc["annotations"] if not a["iscrowd"]]
    (tmp_path / "perfect.json").write_text(json.dumps(perfect))
    assert main([*args, "--external", f"oracle={tmp_path / 'perfect.json'}"]) == 0
    again = json.loads((report / "report.json").read_text())
    assert again["models"]["oracle"]["strict"]["0.5"]["recall"] == 1.0
    assert "\n| oracle | 1.000 |" in (report / "report.md").read_text()  # a row of the comparison
    for kind in (MULTI, SINGLE, BEV):
        reused = again["timings"][f"train {kind}"]
        assert reused["reused"] and reused["trained_seconds"] == pytest.approx(result["timings"][f"train {kind}"])
        sel = result["models"][kind]["selection"]  # checkpoint and threshold chosen on validation
        assert sel["checkpoint"] in ("latest.pt", "best.pt") and sel["threshold"] in (0.01, 0.45)
        assert sel["eval_stats"] in ("running", "item") and f"{sel['eval_stats']} batch-norm statistics" in text
        if kind != BEV:
            assert sel["nms_iou"] in load_preset("smoke").nms_grid and f"NMS IoU {sel['nms_iou']}" in text
        else:  # merged in the world, not by 2D NMS
            assert sel["nms_iou"] is None
        assert sel["depth_gap"] in (load_preset("smoke").depth_gaps if kind == MULTI else (None,))  # no distances
        sweep = result["models"][kind]["test_threshold_sweep"]  # the test split at every candidate threshold
        assert [r["threshold"] for r in sweep] == [0.01, 0.45] and sweep[0]["recall"] >= sweep[1]["recall"]
    assert "depth gap of depth-gated NMS (of none, 4 m)" in text
    assert again["models"][MULTI]["strict"] == result["models"][MULTI]["strict"]  # deterministic evaluation
    # a stored run trained otherwise (here without pose noise, or with another learning rate) is not reused
    for setting in ("bev:train.pose_noise=[0.2,0.2]", "bev:train.lr=0.01"):
        assert main([*args, "--models", "bev", "--set-model", setting]) == 2
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert "holds a bev run with another configuration" in err and setting.split(":")[1].split("=")[0] in err


@pytest.mark.blender
@pytest.mark.slow
def test_a_subset_of_the_models_and_models_on_other_grids(smoke, tmp_path):
    """A subset of the preset's models: the others are not evaluated, their runs stay; the full run's
    pose-noise rows set beside the subset's in its robustness table."""
    out, args, _ = smoke
    report = out / "report"
    again = json.loads((report / "report.json").read_text())
    (tmp_path / "full.json").write_text((report / "report.json").read_text())
    assert main([*args, "--models", "bev,single-view", "--sweep-beside", f"full={tmp_path / 'full.json'}"]) == 0
    subset = json.loads((report / "report.json").read_text())
    assert set(subset["models"]) == {SINGLE, BEV, own_view_name(BEV), late_fusion_name(BEV), late_into_name(BEV, SINGLE)}
    full_f1 = again["models"][MULTI]["pose_noise_sweep"]["0"]["f1"]
    assert f"| {MULTI} (full) | {full_f1:.3f} | " in (report / "report.md").read_text() and subset["pose_noise_beside"]
    assert (out / "runs" / MULTI / "latest.pt").is_file()
    # models on different grids (a finer single view) are each scored on their own items: the same road
    # users and views, no fusion (it pairs cells of one grid)
    mixed = tmp_path / "mixed"
    assert main(["smoke", "--out", str(mixed), "--data", str(out / "dataset"), "--quiet", "--models",
                 f"{MULTI},{SINGLE}", "--set-model", f"{SINGLE}:data.cell_px=6"]) == 0
    got = json.loads((mixed / "report" / "report.json").read_text())["models"]
    assert "fusion" not in got and got[SINGLE]["ground_truth"] == got[MULTI]["ground_truth"] > 0
    assert got[SINGLE]["views"] == got[MULTI]["views"]


@pytest.mark.blender
@pytest.mark.slow
def test_the_two_test_sets_and_the_placement_reach_the_report(smoke):
    """Issue 85: each row on the built-in and the new layouts (one frame, one drawn lighting each); issue 87: where
    the model with 3D detections places what it finds, from the results file the devkit scored."""
    out, _, result = smoke
    text = (out / "report" / "report.md").read_text()
    sets = result["analyses"]["test_sets"]["sets"]
    assert [sets[k]["scenarios"] for k in ("built-in", "new layouts")] == [["intersection_03"], ["procedural-20000"]]
    assert set(sets["new layouts"]["rows"]) == set(result["models"]) and "## Two test sets" in text
    new = Dataset.open(out / "dataset").scenario("procedural-20000")
    assert new.frames == 1 and len(new.lighting) == 1
    if devkit_available():
        placement = result["analyses"]["placement"][BEV]
        assert set(placement) == {"car", "pedestrian"} and "radial share" in text
        assert all(f["matches"] <= f["predictions"] for f in placement.values())


@pytest.mark.blender
@pytest.mark.slow
def test_every_stated_difference_in_the_report_carries_its_standard_error(smoke):
    """Issue 85: a difference the report states is followed by its standard error, or by the words saying why there
    is none (``report_text``)."""
    bare = bare_differences((smoke[0] / "report" / "report.md").read_text())
    assert not bare, bare[:5]


def test_bench_rejects_bad_options(capsys):
    assert main(["smoke", "--steps", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--steps" in err
    assert main(["smoke", "--out", "/nonexistent/never", "--set", "model.loss.obj_loss=xyz"]) == 2  # before rendering
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "model.loss.obj_loss" in err
    assert main(["smoke", "--out", "/nonexistent/never", "--set-model", f"{SINGLE}:train.background_rays=0"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "train.background_rays" in err
    assert main(["nonsense"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "unknown benchmark preset 'nonsense'" in err and "cpu, cpu_hires, cpu_pretrained, cpu_seq, cpu_variety, demo, gpu, gpu_quick, smoke" in err
    assert main(["missing/preset.yaml"]) == 2
    assert "missing/preset.yaml does not exist" in capsys.readouterr().err


@pytest.mark.blender
@pytest.mark.slow
def test_every_registered_kind_runs_through_the_bench_one_from_another_package_too(smoke, example_kind_package,
                                                                                   tmp_path):
    """The preset's kinds ran above; every other registered kind (here ground-mean, installed from
    tests/example_kind and found by its entry point) runs through the smoke preset on the same data."""
    import os
    import subprocess
    import sys

    from pnyolo.registry import kinds

    out, _, _ = smoke
    root = REPO
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(example_kind_package), str(root)])}
    others = ["ground-mean", *(k for k in kinds() if k not in load_preset("smoke").models)]
    for kind in others:
        res = subprocess.run([sys.executable, "-m", "pnyolo.bench.cli", "smoke", "--out", str(tmp_path / kind),
                              "--data", str(out / "dataset"), "--quiet", "--models", kind], env=env,
                             capture_output=True, text=True, timeout=1200)
        assert res.returncode == 0, res.stderr[-3000:]
        result = json.loads((tmp_path / kind / "report" / "report.json").read_text())
        assert set(result["models"]) == {kind, own_view_name(kind), late_fusion_name(kind)}  # from its abilities
        text = (tmp_path / kind / "report" / "report.md").read_text()
        assert f"- `{kind}`: " in text and f"**Late fusion** (`{late_fusion_name(kind)}`)" in text


@pytest.mark.blender
@pytest.mark.slow
def test_the_benchs_model_chance_and_into_rows_are_the_command_lines(smoke, tmp_path):
    """Issue 86: ``--point-from BENCH`` gives the checkpoint, the ``--chance-from`` single view and the ``--into`` ego
    the points the bench chose on validation (and the late fusion into it its two thresholds), ``--late-rule
    from:BENCH`` late fusion its rule, ``--own-view`` the ablation: the command line's rows equal the bench's, every
    one (both predict through one plan, ``pnyolo.bench.plan``)."""
    from pnyolo.cli import eval_main

    out, _, result = smoke
    bench = tmp_path / "report.json"  # the first run's record (the module's later runs write over the folder's)
    bench.write_text(json.dumps(result))
    ckpt = lambda k: str(out / "runs" / k / result["models"][k]["selection"]["checkpoint"])  # noqa: E731
    common = ["--every-camera", str(out / "dataset"), "--split", "test", "--point-from", str(bench), "--quiet"]
    assert eval_main([ckpt(MULTI), *common, "--chance-from", ckpt(SINGLE), "--out", str(tmp_path / "c")]) == 0
    mine = json.loads((tmp_path / "c" / "metrics.json").read_text())
    assert eval_main([ckpt(MULTI), *common, "--own-view", "--out", str(tmp_path / "o")]) == 0  # the ablation's row
    own = json.loads((tmp_path / "o" / "comparison.json").read_text())["models"]
    for name in (MULTI, own_view_name(MULTI)):
        assert own[name]["strict"] == result["models"][name]["strict"], name
    group = "hidden here, seen in another view"  # chance: the single view's recall on the same objects
    hidden = lambda k: result["models"][k]["recall_by_visibility"]["0.2"][group]["recall"]  # noqa: E731
    assert mine["strict"] == result["models"][MULTI]["strict"] and mine["ap50"] == result["models"][MULTI]["ap50"]
    assert mine["against_chance"]["chance"] == hidden(SINGLE) and mine["against_chance"]["recall"] == hidden(MULTI)
    # issue 76: --late-rule from:BENCH gives late fusion the bench's rule and point; argument order is free
    assert eval_main(["--late-fusion", ckpt(BEV), "--late-rule", f"from:{bench}", *common, "--into", ckpt(SINGLE),
                      "--out", str(tmp_path / "i")]) == 0
    mine = json.loads((tmp_path / "i" / "comparison.json").read_text())
    rows, late, into = mine["models"], late_fusion_name(BEV), late_into_name(BEV, SINGLE)
    for name in (late, into, SINGLE):  # late fusion, late fusion into the ego, the ego at its own chosen point
        assert rows[name]["strict"] == result["models"][name]["strict"], name
    assert rows[late]["ap50"] == result["models"][late]["ap50"]
    assert rows[late]["standard_errors"] == result["models"][late]["standard_errors"]
    assert mine["late_fusion"]["rule"] == result["models"][late]["late_fusion_selection"]["rule"]
