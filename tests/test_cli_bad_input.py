"""Every console script answers bad input with one line naming the problem and a non-zero exit,
checked before any work: no traceback, no silent success, nothing left that looks complete."""
from __future__ import annotations

import os
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from test_pnyolo_common import TINY, make_dataset

from blender_tools.cli import main as blender_gen
from dataset_spec import Dataset
from dataset_spec.cli import main as dataset_spec_cli
from pnyolo.bench.cli import main as pnyolo_bench
from pnyolo.cli import eval_main as pnyolo_eval
from pnyolo.cli import train_main as pnyolo_train
from tools.projection_cli import main as project_labels
from tools.viewer_cli import main as seg_viewer

COMMANDS = {"blender-gen": blender_gen, "dataset-spec": dataset_spec_cli, "project-labels": project_labels,
            "seg-viewer": seg_viewer, "pnyolo-train": pnyolo_train, "pnyolo-eval": pnyolo_eval,
            "pnyolo-bench": pnyolo_bench}
READ_ONLY = Path("/sys/pnyolo-test-out")  # read-only even for root


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A labelled dataset, a trained checkpoint and the broken inputs the cases use."""
    tmp = tmp_path_factory.mktemp("bad")
    ds = make_dataset(tmp / "ds", n_scenarios=2)
    sets = sum((["--set", s] for s in TINY + ["train.max_steps=2", "train.epochs=1"]), [])
    assert pnyolo_train([str(ds), "--out", str(tmp / "run"), "--quiet", *sets]) == 0
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
    ckpt = torch.load(tmp / "run" / "latest.pt", weights_only=False)
    ckpt["config"]["model"]["mlp"]["hidden"] = 48  # weights built with 32
    torch.save(ckpt, tmp / "tampered.pt")
    return tmp


def _cases():
    F = "{tmp}/afile"
    return [  # (command, argv, words the one line must hold, paths that must not exist afterwards)
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
        ("blender-gen", ["render", "--blend", "{tmp}/street.blend", "--scene", "../../x", "--out", "{tmp}/b2"],
         ["--scene '../../x'", "letters, digits"], ["{tmp}/b2"]),
        ("pnyolo-eval", ["{tmp}/run", "{tmp}/ds"], ["run: is a folder; expected a checkpoint file"], []),
        ("blender-gen", ["render", "--scene", "toy", "--hdr-dir", F, "--out", "{tmp}/b3"], ["is a file; expected a folder"],
         ["{tmp}/b3"]),
        ("pnyolo-bench", ["nonsense"], ["unknown benchmark preset 'nonsense'"], []),
        # the ground-plane model and late fusion: what they need, said before any work
        ("pnyolo-train", ["{tmp}/no_boxes", "--out", "{tmp}/r6"], ["toy_01/", "has no 3D box in the scenario's actor"],
         ["{tmp}/r6"]),
        ("pnyolo-eval", ["{tmp}/run/latest.pt", "{tmp}/no_boxes", "--split", "train", "--out", "{tmp}/e4"], ["has no 3D box"], ["{tmp}/e4"]),
        ("pnyolo-train", ["{tmp}/ds", "--out", "{tmp}/r7", "--set", "model.kind=bev",
                          "--set", "model.bev.bounds=[500,500,600,600]"], ["model.bev.bounds", "cover no camera's view"],
         ["{tmp}/r7"]),
        ("pnyolo-train", ["{tmp}/ds", "--out", "{tmp}/r8", "--set", "model.kind=bev", "--set", "model.bev.max_cells=100"],
         ["above model.bev.max_cells"], ["{tmp}/r8"]),
        ("pnyolo-eval", ["{tmp}/run/latest.pt", "{tmp}/ds", "--late-fusion", "--out", "{tmp}/e3"],
         ["--late-fusion needs a model with 3D detections"], ["{tmp}/e3"]),
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
