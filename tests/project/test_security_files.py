"""Files from others, round two (issue 62): ONNX files whose digest was recomputed, links planted at every
default output of every command, frame counts and alias bombs that would allocate before being checked. The
checkpoint and dataset attacks of round one live in tests/project/test_security.py, whose fixture this module shares."""
from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from test_pnyolo_common import TINY
from test_security import _broken, _edit_scenario, world  # noqa: F401 - the shared fixture

from dataset_spec.validate import validate
from pnyolo.cli import eval_main, train_main
from pnyolo.cli.export import main as export_main
from pnyolo.cli.predict import main as predict_main
from tools.projection_cli import main as labels_main


# ------------------------------------------------------------------------------------ ONNX files
def _reseal_digest(proto) -> None:
    """What an attacker can do with an unkeyed digest kept in the file: recompute it over the changed graph."""
    import hashlib

    from pnyolo.onnx.integrity import _message

    meta = {p.key: p.value for p in proto.metadata_props}
    for p in proto.metadata_props:
        if p.key == "pnyolo.graph_digest":
            p.value = hashlib.sha256(_message(proto, meta)).hexdigest()


def test_an_onnx_file_with_changed_weights_is_refused_even_with_its_digest_recomputed(world, tmp_path, capsys):
    """Issue 62, item 5: zeroed weights and a recomputed digest once gave 432 detections instead of refusal."""
    onnx = pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    from onnx import numpy_helper

    ckpt = world / "run" / "latest.pt"
    assert export_main([str(ckpt), "--onnx", str(tmp_path / "m.onnx"), "--size", "64x48"]) == 0
    assert (tmp_path / "m.onnx.sha256").read_text().endswith("  m.onnx\n")  # the detached digest, sha256sum's way
    proto = onnx.load(str(tmp_path / "m.onnx"))
    for init in proto.graph.initializer:
        init.CopyFrom(numpy_helper.from_array(np.zeros_like(numpy_helper.to_array(init)), init.name))
    onnx.save(proto, str(tmp_path / "zeroed.onnx"))
    argv = [str(ckpt), str(world / "ds"), "--backend", "onnxruntime", "--out", str(tmp_path / "p")]
    assert predict_main([*argv, "--onnx", str(tmp_path / "zeroed.onnx")]) == 2  # an accident: the digest
    assert "changed after export" in capsys.readouterr().err
    _reseal_digest(proto)
    onnx.save(proto, str(tmp_path / "resealed.onnx"))
    assert predict_main([*argv, "--onnx", str(tmp_path / "resealed.onnx")]) == 2  # an attack: the binding
    assert "not bound to this checkpoint" in capsys.readouterr().err
    assert predict_main([*argv, "--onnx", str(tmp_path / "resealed.onnx"), "--onnx-sha256",
                         str(tmp_path / "m.onnx.sha256")]) == 2  # the digest the user kept: refused before any work
    assert "not the one you kept" in capsys.readouterr().err and not (tmp_path / "p").exists()
    digest = (tmp_path / "m.onnx.sha256").read_text().split()[0]
    assert predict_main([*argv, "--onnx", str(tmp_path / "m.onnx"), "--onnx-sha256", digest, "--quiet"]) == 0


def test_an_onnx_file_is_checked_before_a_runtime_session_exists(world, tmp_path, capsys, monkeypatch):
    """Rule (issue 84 item 3): integrity before work: a changed file is refused from its bytes and metadata before ONNX
    Runtime builds a session (which already folds constants, a ConstantOfShape chain's gigabytes included)."""
    onnx = pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    ckpt = world / "run" / "latest.pt"
    assert export_main([str(ckpt), "--onnx", str(tmp_path / "m.onnx"), "--size", "64x48"]) == 0
    proto = onnx.load(str(tmp_path / "m.onnx"))
    proto.graph.node[0].name = "changed"
    _reseal_digest(proto)
    onnx.save(proto, str(tmp_path / "changed.onnx"))
    sessions = []
    real = ort.InferenceSession
    monkeypatch.setattr(ort, "InferenceSession", lambda *a, **k: sessions.append(1) or real(*a, **k))
    argv = [str(ckpt), str(world / "ds"), "--backend", "onnxruntime", "--out", str(tmp_path / "p"), "--quiet"]
    assert predict_main([*argv, "--onnx", str(tmp_path / "changed.onnx")]) == 2
    assert "not bound to this checkpoint" in capsys.readouterr().err and sessions == []
    assert predict_main([*argv, "--onnx", str(tmp_path / "m.onnx")]) == 0 and sessions  # the file as exported runs


@pytest.mark.parametrize("key,value,words", [("pnyolo.views", "three", "pnyolo.views 'three' is not a number"),
                                             ("pnyolo.size", "60000x60000", "pnyolo.size '60000x60000' is not"),
                                             ("pnyolo.size", "64x48", "changed after export")])
def test_the_metadata_the_runtime_trusts_is_range_checked_and_covered_by_the_digest(world, tmp_path, capsys, key,
                                                                                   value, words):
    onnx = pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    ckpt = world / "run" / "latest.pt"
    assert export_main([str(ckpt), "--onnx", str(tmp_path / "m.onnx"), "--size", "64x32"]) == 0
    proto = onnx.load(str(tmp_path / "m.onnx"))
    for p in proto.metadata_props:
        if p.key == key:
            p.value = value
    onnx.save(proto, str(tmp_path / "meta.onnx"))
    assert predict_main([str(ckpt), str(world / "ds"), "--backend", "onnxruntime", "--onnx", str(tmp_path / "meta.onnx"),
                         "--out", str(tmp_path / "p")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and words in err and "Traceback" not in err, err


# --------------------------------------------------------------------------------- links in output folders
def _link_cases(world: Path, tmp: Path) -> dict:
    """Each command with a link planted where it writes by default, or inside the --out it is given."""
    from dataset_spec.cli import main as spec_main
    from pnyolo.cli.track import main as track_main
    from tools.viewer_cli import main as viewer_main

    ds = shutil.copytree(world / "ds", tmp / "ds")
    run = shutil.copytree(world / "run", tmp / "run", ignore=shutil.ignore_patterns("eval_*", "tracks_*"))
    bev = shutil.copytree(world / "bev", tmp / "bev", ignore=shutil.ignore_patterns("eval_*", "tracks_*"))
    ckpt, bev_ckpt = str(run / "latest.pt"), str(bev / "latest.pt")
    out = tmp / "chosen"
    out.mkdir()
    resume = shutil.copytree(world / "run", tmp / "resume")
    (resume / "log.jsonl").unlink()
    sets = sum((["--set", s] for s in TINY + ["train.max_steps=3", "train.epochs=1"]), [])
    return {  # name: (where the link goes, the command)
        "project-labels default": (ds / "exports", lambda: labels_main([str(ds), "--no-labelling", "--export", "yolo"])),
        "project-labels format folder": (ds / "exports" / "coco", lambda: labels_main(
            [str(ds), "--no-labelling", "--export", "coco"])),
        "project-labels --out subfolder": (out / "kitti", lambda: labels_main(
            [str(ds), "--no-labelling", "--export", "kitti", "--out", str(out)])),
        "seg-viewer default": (ds / "viewer", lambda: viewer_main([str(ds), "--no-html", "--quiet"])),
        "pnyolo-eval default": (run / "eval_train", lambda: eval_main([ckpt, str(ds), "--split", "train", "--quiet"])),
        "pnyolo-eval --late-fusion --out subfolder": (out / "bev", lambda: eval_main(
            [bev_ckpt, str(ds), "--split", "train", "--every-camera", "--late-fusion", "--out", str(out), "--quiet"])),
        "pnyolo-track default": (bev / "tracks_train", lambda: track_main([bev_ckpt, str(ds), "--split", "train",
                                                                          "--quiet"])),
        "pnyolo-predict --out subfolder": (out / "pictures", lambda: predict_main(
            [ckpt, str(ds), "--split", "train", "--pictures", "1", "--out", str(out), "--quiet"])),
        "dataset-spec info --plots": (tmp / "plots", lambda: spec_main(["info", str(ds), "--plots", str(tmp / "plots")])),
        "pnyolo-train --resume log": (resume / "log.jsonl", lambda: train_main(
            [str(ds), "--out", str(resume), "--resume", "--quiet", *sets])),
    }


@pytest.fixture(scope="module")
def bev_world(world):
    sets = sum((["--set", s] for s in ["model.kind=bev", "model.encoder.backbone=resnet18", "model.encoder.num_layers=2",
                                       "model.encoder.norm=frozen_batch", "data.image_scale=1.0", "data.cell_px=8",
                                       "train.threads=2", "train.val_every=0", "train.max_steps=2", "train.epochs=1"]),
               [])
    assert train_main([str(world / "ds"), "--out", str(world / "bev"), "--quiet", *sets]) == 0
    return world


@pytest.mark.parametrize("case", ["project-labels default", "project-labels format folder",
                                  "project-labels --out subfolder", "seg-viewer default", "pnyolo-eval default",
                                  "pnyolo-eval --late-fusion --out subfolder", "pnyolo-track default",
                                  "pnyolo-predict --out subfolder", "dataset-spec info --plots",
                                  "pnyolo-train --resume log"])
def test_a_link_planted_at_a_default_or_inside_a_chosen_output_sends_nothing_to_its_target(bev_world, tmp_path, case,
                                                                                          capsys):
    """Issue 62, item 2: outputs are written only through real folders (55 files of an export once went to the
    link's target)."""
    where, command = _link_cases(bev_world, tmp_path)[case]
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "secret.txt").write_text("{}\n")
    where.parent.mkdir(parents=True, exist_ok=True)
    os.symlink(victim / "secret.txt" if where.name == "log.jsonl" else victim, where)
    rc = command()
    err = capsys.readouterr().err
    assert rc != 0 and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1 and "link" in err, err
    assert sorted(p.name for p in victim.iterdir()) == ["secret.txt"] and (victim / "secret.txt").read_text() == "{}\n"


def test_a_frame_count_beyond_the_format_s_maximum_is_refused_before_anything_is_built(world, tmp_path, capsys):
    """Issue 62, item 4: sequence.frames 10^10 once made every reader build a list of them (MemoryError)."""
    from dataset_spec.layout import MAX_FRAMES
    from tools.viewer_cli import main as viewer_main

    root = shutil.copytree(world / "ds", tmp_path / "ds")
    _edit_scenario(root, lambda obj: obj.update(sequence={"frames": 10_000_000_000, "fps": 2.0}))
    for run in (lambda: labels_main([str(root), "--no-labelling", "--export", "mot", "--out", str(tmp_path / "x")]),
                lambda: viewer_main([str(root), "--frame", "all", "--out", str(tmp_path / "v")]),
                lambda: predict_main([str(world / "run" / "latest.pt"), str(root), "--split", "train", "--out",
                                      str(tmp_path / "p")])):
        assert run() == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and f"frames 1..{MAX_FRAMES}" in err, err
    problems = [p for p in validate(root) if p.severity == "error"]
    assert problems and f"frames 1..{MAX_FRAMES}" in str(problems[0])


def _bomb(levels: int = 9) -> str:
    """A YAML alias bomb of a few hundred bytes: 9 levels of 9 aliases each (9^9 values once expanded)."""
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{k}: &a{k} [" + ", ".join([f"*a{k - 1}"] * 9) + "]" for k in range(1, levels)]
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("key", ["data.variants", "train.pose_noise", "model.bev.heights"])
def test_an_alias_bomb_in_a_list_valued_key_is_refused_while_loading_in_one_short_line(world, tmp_path, capsys, key):
    """Issue 62, item 6: 320 bytes once gave a 28 MB error line; 406 bytes ran past 100 s at 4.8 GB."""
    section, name = key.rsplit(".", 1)
    text = _bomb() + "\n".join(f"{'  ' * i}{part}:" for i, part in enumerate(section.split("."))) + \
        f"\n{'  ' * len(section.split('.'))}{name}: *a8\n"
    config = tmp_path / "bomb.yaml"
    config.write_text(text.replace("model:\n  bev:", "model:\n  kind: bev\n  bev:"))  # bev's own section
    assert len(config.read_bytes()) < 700
    t0 = time.perf_counter()
    assert train_main([str(world / "ds"), "--config", str(config), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert time.perf_counter() - t0 < 10 and len(err) < 400 and "expands to more than" in err, err[:300]
    preset = tmp_path / "bomb_preset.yaml"
    preset.write_text(_bomb() + "description: d\nsplits: {train: [intersection_01], val: [intersection_02], "
                                "test: [intersection_03]}\nrender: *a8\n")
    from pnyolo.bench.cli import main as bench_main

    assert bench_main([str(preset), "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert len(err) < 400 and "expands to more than" in err, err[:300]


def test_a_checkpoint_config_with_shared_references_is_refused_like_a_yaml_bomb(world, tmp_path, capsys):
    nested = ["noon"] * 9
    for _ in range(8):
        nested = [nested] * 9  # one list shared nine times per level: what pickle's memo stores as a few bytes
    bad = _broken(world, "shared", lambda c: c["config"]["data"].update(variants=nested))
    assert bad.stat().st_size < 2 * (world / "run" / "latest.pt").stat().st_size
    assert eval_main([str(bad), str(world / "ds"), "--out", str(tmp_path / "e")]) == 2
    err = capsys.readouterr().err
    assert len(err) < 400 and "expands to more than" in err, err[:300]
