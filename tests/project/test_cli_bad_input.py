"""Every console script answers bad input with one line naming the problem and a non-zero exit,
checked before any work: no traceback, no silent success, nothing left that looks complete."""
from __future__ import annotations

import json
import os
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from test_pnyolo_common import TINY, make_dataset, tiny

from blender_tools.cli import main as blender_gen
from dataset_spec import Dataset
from dataset_spec.cli import main as dataset_spec_cli
from pnyolo.bench.cli import main as pnyolo_bench
from pnyolo.cli import eval_main as pnyolo_eval
from pnyolo.cli.export import main as pnyolo_export
from pnyolo.cli.predict import main as pnyolo_predict
from pnyolo.cli.track import main as pnyolo_track
from pnyolo.cli import train_main as pnyolo_train
from tools.projection_cli import main as project_labels
from tools.viewer_cli import main as seg_viewer

COMMANDS = {"blender-gen": blender_gen, "dataset-spec": dataset_spec_cli, "project-labels": project_labels,
            "seg-viewer": seg_viewer, "pnyolo-train": pnyolo_train, "pnyolo-eval": pnyolo_eval,
            "pnyolo-predict": pnyolo_predict, "pnyolo-track": pnyolo_track, "pnyolo-export": pnyolo_export,
            "pnyolo-bench": pnyolo_bench}
READ_ONLY = Path("/sys/pnyolo-test-out")  # read-only even for root


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A labelled dataset, a trained checkpoint and the broken inputs the cases use."""
    tmp = tmp_path_factory.mktemp("bad")
    ds = make_dataset(tmp / "ds", n_scenarios=2)
    sets = sum((["--set", s] for s in TINY + ["train.max_steps=2", "train.epochs=1"]), [])
    assert pnyolo_train([str(ds), "--out", str(tmp / "run"), "--quiet", *sets]) == 0
    sv = sum((["--set", s] for s in tiny("model.kind=single-view", "train.max_steps=2", "train.epochs=1")), [])
    assert pnyolo_train([str(ds), "--out", str(tmp / "sv"), "--quiet", *sv]) == 0
    (tmp / "afile").write_text("not a folder")
    bad_inst = shutil.copytree(ds, tmp / "bad_inst")
    d = Dataset.open(bad_inst)
    view = d.layout.instance("toy_01", d.scenario("toy_01").cameras[0].name)
    cv2.imwrite(str(view), np.zeros((10, 12), np.uint16))  # the wrong size for its camera
    (tmp / "garbage.hdr").write_bytes(b"#?RADIANCE\nnot really")
    (tmp / "street.blend").write_bytes(b"BLENDER-v500" + bytes(64))  # a .blend header, enough for the up-front checks
    no_boxes = shutil.copytree(ds, tmp / "no_boxes")  # labels of a road user the actor table lost
    d = Dataset.open(no_boxes)
    scn = d.scenario("toy_01")
    labelled = {lab.instance_id for c in scn.cameras for lab in d.read_labels("toy_01", c.name).objects
                if lab.cls in d.info.detectable_classes}
    lost = min(labelled)
    d.write_scenario(replace(scn, actors=[a for a in scn.actors if a.id != lost]))
    bad_rgb = shutil.copytree(ds, tmp / "bad_rgb")  # RGB files that do not decode
    for rgb in bad_rgb.rglob("rgb/*.png"):
        rgb.write_bytes(b"\x89PNG\r\n\x1a\nbroken")
    for labels in shutil.copytree(ds, tmp / "no_labels").rglob("labels.json"):
        labels.unlink()
    (tmp / "list.yaml").write_text("- train\n- model\n")
    shutil.copytree(tmp / "run", tmp / "run_tb")
    shutil.rmtree(tmp / "run_tb" / "tensorboard", ignore_errors=True)
    (tmp / "run_tb" / "tensorboard").write_text("a file where the run writes a folder")
    rows = {"bbox3": {"bbox": [1, 2, 3]}, "bboxstr": {"bbox": "1 2 3 4"}, "scorestr": {"score": "high"},
            "bboxnan": {"bbox": [1, float("nan"), 3, 4]}, "bboxneg": {"bbox": [1, 2, -3, 4]},
            "scorenan": {"score": float("nan")}, "idtrue": {"image_id": True}}
    for name, change in rows.items():
        row = {"image_id": 1, "category_id": 1, "bbox": [1.0, 2.0, 3.0, 4.0], "score": 0.5, **change}
        (tmp / f"{name}.json").write_text(json.dumps([row]))
    ckpt = torch.load(tmp / "run" / "latest.pt", weights_only=False)
    ckpt["config"]["model"]["mlp"]["hidden"] = 48  # weights built with 32
    torch.save(ckpt, tmp / "tampered.pt")
    return tmp


def _cases():
    """(command, argv, words the one line must hold, paths that must not exist afterwards)."""
    return [*_cases_io(), *_cases_models(), *_cases_round_five(), *_cases_plan()]


def _cases_io():
    F = "{tmp}/afile"
    return [  # outputs, datasets, options and configs
        # an output that cannot be written: refused before any work
        ("pnyolo-train", ["{tmp}/ds", "--out", F + "/run"], ["afile is a file, so no folder"], []),
        ("pnyolo-train", ["{tmp}/ds", "--out", F], ["--out", "is a file, not a folder"], []),
        ("pnyolo-train", ["{tmp}/ds", "--out", str(READ_ONLY)], ["cannot write in /sys"], []),
        ("pnyolo-eval", ["{tmp}/run/latest.pt", "{tmp}/ds", "--out", F], ["--out", "is a file"], []),
        ("project-labels", ["{tmp}/ds", "--export", "yolo", "--out", F + "/x"], ["so no folder"], ["{tmp}/ds/exports"]),
        ("project-labels", ["{tmp}/ds", "--export", "coco", "--out", str(READ_ONLY)], ["cannot write in /sys"], []),
        ("seg-viewer", ["{tmp}/ds", "--out", F + "/v"], ["so no folder"], ["{tmp}/ds/viewer"]),
        ("blender-gen", ["render", "--scene", "toy", "--out", "{tmp}/new_ds", "--timings", F + "/t.json"],
         ["--timings", "so no folder"], ["{tmp}/new_ds"]),
        ("blender-gen", ["render", "--scene", "toy", "--out", F + "/ds"], ["so no folder"], []),
        ("pnyolo-bench", ["smoke", "--out", F + "/b"], ["--out", "so no folder"], []),
        # a view whose segmentation has the wrong size: the validator's message, not a traceback
        ("project-labels", ["{tmp}/bad_inst"], ["instance.png", "differs from camera resolution"], []),
        ("seg-viewer", ["{tmp}/bad_inst", "--out", "{tmp}/view_bad"], ["instance.png", "differs from camera"],
         ["{tmp}/view_bad"]),
        # impossible numbers, checked where the config and the options are read
        ("pnyolo-train", ["{tmp}/ds", "--out", "{tmp}/r1", "--set", "train.lr=-1"], ["train.lr must be > 0"],
         ["{tmp}/r1"]),
        ("pnyolo-train", ["{tmp}/ds", "--out", "{tmp}/r2", "--set", "train.epochs=0"], ["train.epochs must be >= 1"],
         ["{tmp}/r2"]),
        ("pnyolo-train", ["{tmp}/ds", "--out", "{tmp}/r3", "--set", "eval.nms_iou=2"], ["eval.nms_iou"], ["{tmp}/r3"]),
        ("pnyolo-eval", ["{tmp}/run/latest.pt", "{tmp}/ds", "--conf", "-1"], ["--conf must be in [0, 1]"], []),
        ("pnyolo-eval", ["{tmp}/run/latest.pt", "{tmp}/ds", "--conf", "2"], ["--conf must be in [0, 1]"], []),
        ("pnyolo-eval", ["{tmp}/run/latest.pt", "{tmp}/ds", "--nms-iou", "-1"], ["--nms-iou must be in (0, 1]"], []),
        ("pnyolo-eval", ["{tmp}/run/latest.pt", "{tmp}/ds", "--nms-iou", "2"], ["--nms-iou"], []),
        ("pnyolo-eval", ["{tmp}/run/latest.pt", "{tmp}/ds", "--examples", "-1", "--out", "{tmp}/e1"],
         ["--examples must be >= 0"], ["{tmp}/e1"]),
        # an HDR file that is not an image would render as magenta
        ("blender-gen", ["render", "--scene", "toy", "--hdr", "{tmp}/garbage.hdr", "--out", "{tmp}/hdr_ds"],
         ["garbage.hdr", "not a readable Radiance"], ["{tmp}/hdr_ds"]),
        # a run folder that holds a run, and a resume with nothing to resume
        ("pnyolo-train", ["{tmp}/ds", "--out", "{tmp}/run"], ["already holds a training run", "--resume", "--force"],
         []),
        ("pnyolo-train", ["{tmp}/ds", "--out", "{tmp}/r4", "--resume"], ["no checkpoint", "r4/latest.pt"], ["{tmp}/r4"]),
        ("pnyolo-train", ["{tmp}/ds", "--out", "{tmp}/run", "--resume", "--force"], ["exclude each other"], []),
        # weights that do not fit their stored config: which tensor, which key
        ("pnyolo-eval", ["{tmp}/tampered.pt", "{tmp}/ds", "--out", "{tmp}/e2"], ["tensor mlp.", "model.mlp"],
         ["{tmp}/e2"]),
        # messages that say what the path is and what was expected
        ("pnyolo-train", [F, "--out", "{tmp}/r5"], ["afile: is a file; expected a dataset folder"], ["{tmp}/r5"]),
        ("dataset-spec", ["info", F], ["is a file; expected a dataset folder"], []),
        ("dataset-spec", ["split", "{tmp}/ds", "--train", ""], ["--train ''", "names no scenario"], []),
        ("dataset-spec", ["split", "{tmp}/ds", "--val", " , "], ["--val ' , '", "names no scenario"], []),
        ("blender-gen", ["render", "--blend", "{tmp}/street.blend", "--scene", "../../x", "--out", "{tmp}/b2"],
         ["--scene '../../x'", "letters, digits"], ["{tmp}/b2"]),
        ("pnyolo-eval", ["{tmp}/run", "{tmp}/ds"], ["run: is a folder; expected a checkpoint file"], []),
        ("blender-gen", ["render", "--scene", "toy", "--hdr-dir", F, "--out", "{tmp}/b3"], ["is a file; expected a folder"],
         ["{tmp}/b3"]),
        ("pnyolo-bench", ["nonsense"], ["unknown benchmark preset 'nonsense'"], []),
    ]


def _cases_round_five():
    """Issue 83 item 8's bad inputs."""
    return [
        # issue 83 item 8: a value that passes a range's text but is no setting; more processes than items;
        # empty names where a name goes; a seed numpy refuses, before any worker
        ("pnyolo-train", ["{tmp}/ds", "--set", "train.lr=.inf", "--out", "{tmp}/r_inf"], ["train.lr", "> 0"],
         ["{tmp}/r_inf"]),
        ("pnyolo-train", ["{tmp}/ds", "--nproc", "64", "--out", "{tmp}/n64"],
         ["training items, fewer than the 64 one step takes"], ["{tmp}/n64"]),
        ("pnyolo-eval", ["{tmp}/run/latest.pt", "{tmp}/ds", "--chance-from", "", "--out", "{tmp}/e_ch"],
         ["--chance-from needs a single-view checkpoint's path"], ["{tmp}/e_ch"]),
        ("project-labels", ["{tmp}/ds", "--no-labelling", "--export", "nuscenes", "--nuscenes-channels", "",
                            "--out", "{tmp}/x_ch"], ["--nuscenes-channels: camera names, comma-separated"],
         ["{tmp}/x_ch"]),
        ("blender-gen", ["render", "--scene", "toy", "--seed", "-1", "--out", "{tmp}/seed"],
         ["--seed must be an integer in 0.."], ["{tmp}/seed"]),
    ]


def _cases_plan():
    """Issue 86 item 2's bad inputs: the own-view row pnyolo-eval now gives, refused where it means nothing."""
    return [
        ("pnyolo-eval", ["{tmp}/sv/latest.pt", "{tmp}/ds", "--own-view", "--out", "{tmp}/e10"],
         ["--own-view: a single-view model reads its own camera only"], ["{tmp}/e10"]),
        ("pnyolo-eval", ["{tmp}/run/latest.pt", "{tmp}/ds", "--own-view", "--delay-ms", "100", "--out", "{tmp}/e11"],
         ["--own-view reads each camera alone, which no delay changes"], ["{tmp}/e11"]),
        ("pnyolo-eval", ["--results", "{tmp}/bbox3.json", "{tmp}/ds", "--own-view"], ["--own-view needs a checkpoint"],
         []),
    ]


def _cases_models():
    F = "{tmp}/afile"
    return [  # the models' and the bench's inputs
        # the ground-plane model and late fusion: what they need, said before any work
        ("pnyolo-train", ["{tmp}/no_boxes", "--out", "{tmp}/r6"], ["toy_01/", "has no 3D box in the scenario's actor"],
         ["{tmp}/r6"]),
        ("pnyolo-eval", ["{tmp}/run/latest.pt", "{tmp}/no_boxes", "--split", "train", "--out", "{tmp}/e4"], ["has no 3D box"], ["{tmp}/e4"]),
        ("pnyolo-train", ["{tmp}/ds", "--out", "{tmp}/r7", "--set", "model.kind=bev",
                          "--set", "model.bev.bounds=[500,500,600,600]"], ["model.bev.bounds", "cover no camera's view"],
         ["{tmp}/r7"]),
        ("pnyolo-train", ["{tmp}/ds", "--out", "{tmp}/r8", "--set", "model.kind=bev", "--set", "model.bev.max_cells=100"],
         ["above model.bev.max_cells"], ["{tmp}/r8"]),
        ("pnyolo-eval", ["{tmp}/sv/latest.pt", "{tmp}/ds", "--late-fusion", "--out", "{tmp}/e3"],
         ["--late-fusion needs a model with 3D detections", "not single-view"], ["{tmp}/e3"]),
        # tracking's options checked as evaluation's; a refusal names the reason, not an option never given
        ("pnyolo-track", ["{tmp}/run/latest.pt", "{tmp}/ds", "--start", "2", "--out", "{tmp}/t1"],
         ["--start must be in [0, 1]"], ["{tmp}/t1"]),
        ("pnyolo-track", ["{tmp}/run/latest.pt", "{tmp}/ds", "--keep", "nan", "--out", "{tmp}/t2"],
         ["--keep must be in [0, 1], got nan"], ["{tmp}/t2"]),
        ("pnyolo-track", ["{tmp}/run/latest.pt", "{tmp}/ds", "--gate", "nan", "--out", "{tmp}/t3"],
         ["--gate must be a number of standard deviations > 0, got nan"], ["{tmp}/t3"]),
        ("pnyolo-track", ["{tmp}/run/latest.pt", "{tmp}/ds", "--start", "0.2", "--keep", "0.3", "--out", "{tmp}/t5"],
         ["--keep 0.3 must not exceed --start 0.2"], ["{tmp}/t5"]),
        ("pnyolo-track", ["{tmp}/sv/latest.pt", "{tmp}/ds", "--split", "train", "--out", "{tmp}/t4"],
         ["pnyolo-track (tracks on the ground) needs a model with 3D detections", "not single-view"], ["{tmp}/t4"]),
        # options the checkpoint's kind cannot use: refused for that kind, not ignored
        ("pnyolo-eval", ["{tmp}/sv/latest.pt", "{tmp}/ds", "--depth-gap", "2", "--out", "{tmp}/e8"],
         ["--depth-gap: single-view estimates no distances"], ["{tmp}/e8"]),
        ("pnyolo-eval", ["{tmp}/run/latest.pt", "{tmp}/ds", "--depth-gap", "nan", "--out", "{tmp}/e9"],
         ["--depth-gap must be a number of metres > 0"], ["{tmp}/e9"]),
        # another detector's results: each malformed row named, options that need a checkpoint refused
        *[("pnyolo-eval", ["--results", f"{{tmp}}/{name}.json", "{tmp}/ds", "--split", "train", "--out",
                           f"{{tmp}}/r_{name}"], ["detection 0", words], [f"{{tmp}}/r_{name}"])
          for name, words in (("bbox3", "not 4 finite numbers"), ("bboxstr", "not 4 finite numbers"),
                              ("scorestr", "score 'high' is not a finite number"), ("bboxnan", "not 4 finite"),
                              ("bboxneg", "negative width or height"), ("scorenan", "score nan is not a finite"),
                              ("idtrue", "image_id True is neither"))],
        ("pnyolo-eval", ["--results", "{tmp}/bbox3.json", "{tmp}/ds", "--late-fusion"], ["--late-fusion needs a checkpoint"],
         []),
        ("pnyolo-eval", ["--results", "{tmp}/bbox3.json", "{tmp}/ds", "--fuse", "{tmp}/run/latest.pt"],
         ["--fuse needs a checkpoint"], []),
        ("pnyolo-eval", ["{tmp}/run/latest.pt", "{tmp}/ds", "--into", "{tmp}/run/latest.pt", "--out", "{tmp}/e5"],
         ["--into needs --late-fusion"], ["{tmp}/e5"]),
        ("pnyolo-eval", ["{tmp}/run/latest.pt", "{tmp}/ds", "--ego-conf", "0.3", "--out", "{tmp}/e6"],
         ["--ego-conf goes with --into"], ["{tmp}/e6"]),
        ("pnyolo-eval", ["{tmp}/run/latest.pt", "{tmp}/ds", "--late-fusion", "--into", "{tmp}/run/latest.pt",
                         "--ego-conf", "1.5", "--out", "{tmp}/e7"], ["--ego-conf must be"], ["{tmp}/e7"]),
        # data-parallel training: the user's mistakes once, before any worker starts
        ("pnyolo-train", ["{tmp}/ds", "--nproc", "2", "--out", str(READ_ONLY)], ["cannot write in /sys"], []),
        ("pnyolo-train", ["{tmp}/ds", "--nproc", "2", "--out", "{tmp}/n1", "--resume"], ["no checkpoint"], ["{tmp}/n1"]),
        ("pnyolo-train", ["{tmp}/ds", "--nproc", "2", "--out", "{tmp}/run"], ["already holds a training run"], []),
        ("pnyolo-train", ["{tmp}/no_labels", "--nproc", "2", "--out", "{tmp}/n2"], ["have no 2D labels"], ["{tmp}/n2"]),
        # a Ray address that cannot work: refused at once, or within seconds
        ("blender-gen", ["render", "--scene", "toy", "--ray", "127.0.0.1:70000", "--out", "{tmp}/ray1"],
         ["port 70000 is outside 1..65535"], ["{tmp}/ray1"]),
        ("blender-gen", ["render", "--scene", "toy", "--ray", "127.0.0.1:9", "--out", "{tmp}/ray2"],
         ["--ray 127.0.0.1:9: cannot reach a Ray cluster"], ["{tmp}/ray2"]),
        # an export never copies an image that does not decode
        ("project-labels", ["{tmp}/bad_rgb", "--export", "yolo", "--out", "{tmp}/x_rgb"], ["rgb", "toy_01"],
         ["{tmp}/x_rgb"]),
        # configs and run folders in the wrong shape
        ("pnyolo-train", ["{tmp}/ds", "--config", "{tmp}/list.yaml", "--set", "train.lr=0.1", "--out", "{tmp}/r9"],
         ["list.yaml", "expected a mapping"], ["{tmp}/r9"]),
        ("pnyolo-train", ["{tmp}/ds", "--out", "{tmp}/run_tb", "--resume"], ["tensorboard is a file"], []),
        # a camera named twice as a source view, whichever command
        ("pnyolo-predict", ["{tmp}/run/latest.pt", "{tmp}/ds", "--views", "0,0,1", "--out", "{tmp}/p1"],
         ["--views 0,0,1: indices must be distinct"], ["{tmp}/p1"]),
        ("pnyolo-eval", ["{tmp}/run/latest.pt", "{tmp}/ds", "--views", "1,1", "--out", "{tmp}/e5"],
         ["indices must be distinct"], ["{tmp}/e5"]),
        # one model kind's overrides: the form, and a key that kind refuses, before any rendering
        ("pnyolo-bench", ["smoke", "--out", "{tmp}/b4", "--set-model", "lidar:train.lr=1"], ["--set-model", "KIND:KEY=VALUE"],
         ["{tmp}/b4"]),
        ("pnyolo-bench", ["smoke", "--out", "{tmp}/b5", "--set-model", "single-view:train.own_view_dropout=0.5"],
         ["own_view_dropout", "single-view"], ["{tmp}/b5"]),
        # messages that say what is true: a digit int() does not read, a split name that is no split
        ("seg-viewer", ["{tmp}/ds", "--frame", "\u00b2", "--out", "{tmp}/v1"], ["--frame must be a frame index or 'all'"],
         ["{tmp}/v1"]),
        ("pnyolo-export", ["{tmp}/run/latest.pt", "--onnx", "{tmp}/x1.onnx", "--size", "64x48", "--int8", "--calibrate",
                           "{tmp}/ds", "--split", "bogus"], ["--split", "invalid choice: 'bogus'"], ["{tmp}/x1.onnx"]),
    ]


@pytest.mark.parametrize("command,argv,words,absent", _cases(),
                         ids=[f"{c[0]}-{i}" for i, c in enumerate(_cases())])
def test_bad_input_is_one_line_and_a_non_zero_exit(world, capsys, command, argv, words, absent):
    fill = lambda s: s.replace("{tmp}", str(world))  # noqa: E731
    labels = next(Path(world, "ds").rglob("labels.json"))
    before = labels.stat().st_mtime_ns
    try:
        rc = COMMANDS[command]([fill(a) for a in argv])
    except SystemExit as exc:  # argparse's own errors
        rc = exc.code
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc not in (0, None), err
    assert len(lines) == 1 and "Traceback" not in err, err
    for w in words:
        assert fill(w) in lines[0], (w, lines[0])
    for path in absent:
        assert not Path(fill(path)).exists(), f"{path} was created by a refused command"
    assert labels.stat().st_mtime_ns == before, "the dataset's labels were rewritten before the error"
    assert not READ_ONLY.exists()


def test_stale_render_scratch_folders_are_removed_and_live_ones_kept(tmp_path):
    from blender_tools.pipeline import TEMP_PREFIX, remove_stale_temp_dirs

    dead = 2 ** 22 + 12345  # above any pid this machine hands out
    stale, live, other = (tmp_path / f"{TEMP_PREFIX}{dead}_abc", tmp_path / f"{TEMP_PREFIX}{os.getpid()}_def",
                          tmp_path / "blender_gen_notes")
    for d in (stale, live, other):
        d.mkdir()
    (stale / "half.exr").write_bytes(b"x")
    assert remove_stale_temp_dirs(tmp_path) == 1
    assert not stale.exists() and live.exists() and other.exists()


def test_render_workers_get_a_temporary_folder_the_next_run_removes_when_they_were_killed(tmp_path, monkeypatch):
    """Blender makes blender_* folders in its TMPDIR: the workers' TMPDIR is a scratch folder named for
    the driver, so a killed run's folders go with remove_stale_temp_dirs like the driver's own."""
    import tempfile

    from blender_tools.run_support import worker_env
    from blender_tools.pipeline import remove_stale_temp_dirs

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    env = worker_env()
    scratch = Path(env["TMPDIR"])
    assert scratch.parent == tmp_path and f"_{os.getpid()}_" in scratch.name and str(Path.cwd()) in env["PYTHONPATH"]
    (scratch / "blender_a1b2c3").mkdir()  # what a worker's Blender leaves when it is killed
    assert remove_stale_temp_dirs(tmp_path) == 0  # the driver still runs
    dead = tmp_path / scratch.name.replace(f"_{os.getpid()}_", f"_{2 ** 22 + 12345}_")
    scratch.rename(dead)
    assert remove_stale_temp_dirs(tmp_path) == 1 and not dead.exists()


def test_a_run_that_fails_on_its_first_image_does_not_block_the_next(world, capsys):
    sets = sum((["--set", s] for s in TINY + ["train.max_steps=1", "train.epochs=1"]), [])
    out = world / "first_fails"
    assert pnyolo_train([str(world / "bad_rgb"), "--out", str(out), "--quiet", *sets]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "rgb" in err.splitlines()[-1]
    assert not list(out.glob("*.pt"))
    assert pnyolo_train([str(world / "ds"), "--out", str(out), "--quiet", *sets]) == 0  # no --force needed
    assert (out / "latest.pt").is_file()


def test_results_on_a_dataset_of_two_cameras_need_no_views(world, tmp_path, capsys):
    """Scored in items of as many cameras as the scenes have, when that is fewer than 3."""
    two = Dataset.open(shutil.copytree(world / "ds", tmp_path / "two"))
    for name in two.scenario_names():
        scn = two.scenario(name)
        two.write_scenario(replace(scn, cameras=scn.cameras[:2]))
    empty = tmp_path / "none.json"
    empty.write_text("[]")
    assert pnyolo_eval(["--results", str(empty), str(two.root), "--split", "train", "--out", str(tmp_path / "r"),
                        "--quiet"]) == 0
    assert json.loads((tmp_path / "r" / "metrics.json").read_text())["views"] > 0


def test_options_a_kind_cannot_use_are_refused_for_that_kind():
    from dataset_spec.cli_support import UserError
    from pnyolo.cli.options import refuse_for_kind

    class GroundOnly:  # a kind merged in the world, with no image encoder
        kind, tuned, encoder = "ground-only", (), None

    refuse_for_kind(GroundOnly())  # nothing given: nothing refused
    for given, words in (({"nms_iou": 0.3}, "--nms-iou: ground-only is not decoded by 2D NMS"),
                         ({"depth_gap": 2.0}, "--depth-gap: ground-only"),
                         ({"norm_stats": "item"}, "--norm-stats: ground-only has no image encoder")):
        with pytest.raises(UserError, match=words):
            refuse_for_kind(GroundOnly(), **given)
