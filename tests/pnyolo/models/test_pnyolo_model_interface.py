"""The model interface: a new kind written in this file alone trains, validates, is evaluated and
answers the inference API through the same paths as the built-in kinds; the trainer, evaluation,
inference and the bench know the kinds only through that interface; pnyolo's layers import one way."""
from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from test_pnyolo_common import make_dataset, tiny
from torch import nn

from pnyolo.cli import eval_main
from pnyolo.components.renderer import RayOutputs
from pnyolo.config import load_config
from pnyolo.training.train import train
from pnyolo.inference import Detector
from pnyolo.models import build_model, register_model
from pnyolo.registry import unregister_model
from pnyolo.models.yolo_grid import YoloGridModel
from repo_paths import REPO

torch.set_num_threads(2)
ROOT = REPO


class TinyExample(YoloGridModel):
    """The smallest kind: each grid cell's mean colour through a 1x1 convolution, YOLO outputs."""

    description = "a 1x1 convolution on each cell's mean colour"
    reads_other_views = False

    def __init__(self, cfg, num_classes: int):
        super().__init__(cfg, num_classes)
        self.register_buffer("anchors", torch.tensor(cfg.model.head.anchors, dtype=torch.float32))
        self.head = nn.Conv2d(3, len(cfg.model.head.anchors) * (5 + num_classes), 1)

    def forward(self, images, K, camera_to_world, grid, own_view_only: bool = False) -> RayOutputs:
        x = F.adaptive_avg_pool2d(images, (grid.grid_h, grid.grid_w))
        raw = self.head(x).permute(0, 2, 3, 1).reshape(len(x), grid.grid_h, grid.grid_w, len(self.anchors), -1)
        conf = torch.sigmoid(raw[..., 0])
        return RayOutputs(conf, raw[..., 1:5], raw[..., 5:], torch.full_like(conf, float("nan")))


@pytest.fixture(scope="module")
def example_kind():
    register_model("tiny-example")(TinyExample)
    yield "tiny-example"
    unregister_model("tiny-example")


@pytest.fixture(scope="module")
def tiny_ds(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("iface") / "ds", n_scenarios=3)


def test_a_kind_written_in_one_file_trains_validates_evaluates_and_detects(example_kind, tiny_ds, tmp_path, capsys):
    cfg = load_config(None, tiny(f"model.kind={example_kind}", "train.max_steps=2", "train.epochs=2",
                                 "train.val_every=1"))
    summary = train(tiny_ds, cfg, tmp_path / "run", quiet=True)
    assert summary["steps"] == 2 and np.isfinite(summary["last_loss"]) and summary["best_f1"] >= 0  # validated
    events = [json.loads(line)["event"] for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert events.count("step") == 2 and "validation" in events
    assert eval_main([str(tmp_path / "run" / "latest.pt"), str(tiny_ds), "--split", "test", "--out",
                      str(tmp_path / "ev"), "--conf", "0.01"]) == 0
    metrics = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert metrics["strict"]["0.5"]["tp"] + metrics["strict"]["0.5"]["fn"] > 0  # scored against the ground truth
    from dataset_spec import Dataset
    ds = Dataset.open(tiny_ds)
    scn = ds.scenario(ds.split("test")[0])
    det = Detector.load(tmp_path / "run" / "latest.pt")
    res = det.detect([ds.read_rgb(scn.name, c.name, scn.lighting[0].name) for c in scn.cameras], scn.cameras,
                     conf_threshold=0.0)
    assert len(res) == len(scn.cameras) and all(np.isnan(d.distance) for d in res[0]) and res[0]
    capsys.readouterr()
    assert eval_main([str(tmp_path / "run" / "latest.pt"), str(tiny_ds), "--late-fusion"]) == 2  # no 3D detections
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "3D detections" in err and example_kind in err


def test_a_kind_without_rays_refuses_ray_options(example_kind, tiny_ds):
    from pnyolo.data.dataset import MultiViewDataset
    from pnyolo.models import predict_item

    cfg = load_config(None, tiny(f"model.kind={example_kind}"))
    item = MultiViewDataset(tiny_ds, "train", cfg, training=False)[0]
    model = build_model(cfg, 2)
    with pytest.raises(ValueError, match="ray_mask"):
        predict_item(model, item, "cpu", ray_mask=torch.ones(model.targets(item).shape[:3], dtype=torch.bool))
    assert predict_item(model, item, "cpu", ray_mask=None).ray_confidence.shape == model.targets(item).shape[:4]


def _imports(path: Path) -> list[str]:
    return [n.module for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.ImportFrom) and n.module]


# pnyolo's layers, lowest first: a module imports only from its own layer or below.
# "onnx.convention" (the graphs' calling convention: text the kinds' graph_convention fills in, importing nothing)
# is a leaf below the kinds; the rest of onnx exports and runs them.
# ``engine`` (predicting, checkpoints, devices) sits below every analysis; ``training`` validates by their scoring.
LAYERS = [("config", "registry", "onnx.convention"), ("data",), ("components",), ("decoding",), ("models",),
          ("engine",), ("cooperation",), ("evaluation",), ("tracking", "training"), ("inference", "onnx"),
          ("bench", "cli", "devtools")]


def _layer(module: str) -> int | None:
    parts = module.split(".")
    if parts[0] != "pnyolo" or len(parts) < 2:
        return None
    for name in (".".join(parts[1:3]), parts[1]):  # a listed submodule before its package
        k = next((k for k, names in enumerate(LAYERS) if name in names), None)
        if k is not None:
            return k
    return None


def test_pnyolo_layers_import_one_way_and_only_models_know_the_kinds():
    upward, kind_imports = [], []
    for path in sorted((ROOT / "pnyolo").rglob("*.py")):
        module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        here = _layer(module)
        for target in _imports(path):
            there = _layer(target)
            if here is not None and there is not None and there > here:
                upward.append(f"{module} -> {target}")
            if target.startswith("pnyolo.models.") and target not in ("pnyolo.models.base", "pnyolo.models.yolo_grid") \
                    and not module.startswith("pnyolo.models"):
                kind_imports.append(f"{module} -> {target}")
    assert not upward, upward
    assert not kind_imports, kind_imports  # a kind's module is imported by the registry only


def test_every_part_of_pnyolo_has_a_layer_and_its_top_level_holds_few_modules():
    """Issue 66: a subpackage missing from LAYERS escapes the one-way rule (tracking once did); the top level
    holds the registry, the inference API and the package's face, the rest is in subpackages by role."""
    top = ROOT / "pnyolo"
    parts = {p.stem for p in top.glob("*.py") if p.stem != "__init__"} | {
        p.name for p in top.iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
    assert parts <= {n for layer in LAYERS for n in layer}, parts - {n for layer in LAYERS for n in layer}
    assert len([p for p in top.glob("*.py") if p.stem != "__init__"]) <= 6


def test_each_kind_has_its_own_model_section_and_older_checkpoints_still_load():
    from pnyolo.config import from_dict, to_dict
    from pnyolo.engine.checkpoint import checkpoint_config

    bev = load_config(None, tiny("model.kind=bev"))
    assert set(to_dict(bev)["model"]) == {"kind", "encoder", "head", "bev", "loss", "surface_depth"}
    with pytest.raises(Exception, match="has no model.sampler"):
        load_config(None, tiny("model.kind=bev", "model.sampler.num_samples=4"))
    # a shared config file keeps every kind's sections; each kind reads its own
    assert load_config(ROOT / "configs" / "cpu.yaml", ["model.kind=single-view"]).model.kind == "single-view"
    # what older versions wrote: every section for every kind, the ground height in the sampler, one loss section
    legacy = to_dict(load_config(None))
    legacy["model"] = {**legacy["model"], "kind": "bev", "bev": to_dict(bev)["model"]["bev"]}
    legacy["model"]["sampler"]["ground_z"] = 0.5
    del legacy["data"]["ground_z"], legacy["model"]["loss"]
    legacy["loss"] = {"box": 1.0, "obj": 5.0, "occupancy": 0.5, "bev_heatmap": 2.0, "bev_box": 0.25}
    cfg = checkpoint_config({"config": legacy})
    assert cfg.model == from_dict({"model": {**to_dict(bev)["model"], "encoder": legacy["model"]["encoder"],
                                             "head": legacy["model"]["head"],
                                             "loss": {"heatmap": 2.0, "regression": 0.25}}}).model
    assert cfg.data.ground_z == 0.5


def test_a_kinds_signature_is_its_whole_section_but_what_it_declares_run_time():
    from pnyolo.config import to_dict

    for kind, (runtime, own) in {"pixelnerf-yolo": ("chunk_memory_mb=64", "sampler.near=3.0"),
                                 "single-view": ("encoder.eval_stats=item", "head.ignore_threshold=0.4"),
                                 "bev": ("bev.top_k=7", "bev.min_radius=3")}.items():
        cfg = load_config(None, tiny(f"model.kind={kind}"))
        sig = cfg.model.signature()
        section = to_dict(cfg)["model"]
        for key, value in sig.items():  # dotted keys of the section, with their values
            node = section
            for part in key.split("."):
                node = node[part]
            assert node == value, key
        assert not set(sig) & {*cfg.model.runtime_keys, *cfg.model.path_keys}, kind
        assert load_config(None, tiny(f"model.kind={kind}", f"model.{runtime}")).model.signature() == sig
        changed = load_config(None, tiny(f"model.kind={kind}", f"model.{own}")).model.signature()
        assert {k for k in sig if sig[k] != changed[k]} == {own.split("=")[0]}, kind


def test_a_kind_without_an_encoder_has_none_and_its_resume_names_its_own_key(example_kind, tiny_ds, tmp_path, capsys):
    """tiny-example reads no encoder: an encoder key is refused for it, and a change of its own key on resume is
    refused by name before any weight is loaded (before: the encoder key was, and its own key only at loading)."""
    from pnyolo.cli import train_main

    cfg = load_config(None, tiny(f"model.kind={example_kind}"))
    assert not hasattr(cfg.model, "encoder") and "encoder.backbone" not in cfg.model.signature()
    with pytest.raises(Exception, match=f"{example_kind} has no model.encoder"):
        load_config(None, [f"model.kind={example_kind}", "model.encoder.backbone=resnet18"])
    sets = sum((["--set", x] for x in tiny(f"model.kind={example_kind}", "train.max_steps=1", "train.epochs=1")), [])
    run = tmp_path / "run"
    assert train_main([str(tiny_ds), "--out", str(run), "--quiet", *sets]) == 0
    capsys.readouterr()
    assert train_main([str(tiny_ds), "--out", str(run), "--quiet", "--resume", *sets,
                       "--set", "model.head.ignore_threshold=0.3"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "another model config (differs in: model.head.ignore_threshold)" in err, err


def test_a_weight_that_does_not_fit_names_the_key_its_kind_builds_it_from():
    from pnyolo.engine.checkpoint import load_weights
    from dataset_spec.cli_support import UserError

    for kind, sets, key in (("bev", ["model.bev.channels=4"], "model.bev.channels"),
                            ("bev", ["model.bev.hidden=8"], "model.bev"),
                            ("pixelnerf-yolo", ["model.mlp.hidden=16"], "model.mlp"),
                            ("single-view", ["model.head.anchors=[[0.1,0.1]]"], "model.head")):
        with torch.device("meta"):
            ours = build_model(load_config(None, tiny(f"model.kind={kind}")), 2)
            theirs = build_model(load_config(None, tiny(f"model.kind={kind}", *sets)), 2)
        with pytest.raises(UserError, match=f"see config {key}") as err:
            load_weights(ours, theirs.state_dict(), "x.pt", check_only=True)
        assert "\n" not in str(err.value)


def test_a_config_file_of_before_the_move_loads_its_loss_weights_into_the_kind_with_one_line(tmp_path, capsys):
    """The loss weights moved from the top-level ``loss`` into each kind's ``model.loss``: an older file (and
    ``--set loss.KEY``) still loads, each kind taking the weights it reads, with one line naming where they went."""
    path = tmp_path / "old.yaml"
    path.write_text("loss: {obj: 5.0, iou: 1.0, occupancy: 0.5, bev_box: 0.25}\n")
    capsys.readouterr()
    multi = load_config(path)
    assert (multi.model.loss.obj, multi.model.loss.iou, multi.model.loss.occupancy) == (5.0, 1.0, 0.5)
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "loss.obj -> model.loss.obj" in err and "loss.bev_box" not in err
    single = load_config(path, ["model.kind=single-view", "loss.depth=0.1"])
    assert (single.model.loss.obj, single.model.loss.depth) == (5.0, 0.1) and not hasattr(single.model.loss, "occupancy")
    assert load_config(path, ["model.kind=bev"]).model.loss.regression == 0.25
    with pytest.raises(Exception, match="known old keys"):
        load_config(None, ["loss.nope=1"])
    # today's form in a shared file: each kind keeps the loss keys it has
    path.write_text("model:\n  loss: {obj: 5.0, occupancy: 0.5, heatmap: 2.0}\n")
    assert load_config(path, ["model.kind=bev"]).model.loss.heatmap == 2.0
    assert load_config(path, ["model.kind=single-view"]).model.loss.obj == 5.0
    with pytest.raises(Exception, match="single-view has no model.loss.occupancy .that is pixelnerf-yolo's"):
        load_config(None, ["model.kind=single-view", "model.loss.occupancy=1"])


def test_a_shared_file_gives_the_run_s_kind_its_own_sections(tmp_path):
    path = tmp_path / "shared.yaml"
    path.write_text("model:\n  kind: pixelnerf-yolo\n  sampler: {num_samples: 8}\n  bev: {cell_m: 0.2}\n")
    assert load_config(path, ["model.kind=bev"]).model.bev.cell_m == 0.2  # the file's kind is not the run's
    assert load_config(path).model.sampler.num_samples == 8


# ------------------------------------------------------------------------------------ a kind from another package
def _cli(site, module: str, *argv: str) -> subprocess.CompletedProcess:
    """``python -m pnyolo.MODULE ARGV`` in a fresh process whose path holds the installed example package
    (and no edit of pnyolo): ``cli train|eval|predict``, ``cli.export``."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)])}
    return subprocess.run([sys.executable, "-m", f"pnyolo.{module}", *argv], env=env, capture_output=True, text=True,
                          timeout=900)


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_a_multi_view_world_output_kind_in_another_package_registers_trains_exports_and_late_fuses(
        example_kind_package, tiny_ds, tmp_path):
    site = example_kind_package
    found = subprocess.run([sys.executable, "-c", "from pnyolo.registry import kinds; print(sorted(kinds()))"],
                           env={**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)])},
                           capture_output=True, text=True, check=True).stdout
    assert "ground-mean" in found  # by its entry point: pnyolo names it nowhere
    assert "ground-mean" in _cli(site, "cli", "train", "--help").stdout  # --model lists it
    for script in ("config_reference.py", "cli_reference.py"):  # the generated references stay pnyolo's own
        ref = subprocess.run([sys.executable, str(ROOT / "scripts" / script), "--check"], capture_output=True, text=True,
                             env={**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)])}, timeout=600)
        assert ref.returncode == 0, (script, ref.stdout[-500:], ref.stderr[-500:])
    sets = sum((["--set", s] for s in ["model.kind=ground-mean", "train.max_steps=3", "train.epochs=2",
                                       "train.val_every=1", "train.threads=2", "data.image_scale=1.0",
                                       "data.cell_px=8", "train.tensorboard=false"]), [])
    run = _cli(site, "cli", "train", str(tiny_ds), "--out", str(tmp_path / "run"), "--quiet", *sets)
    assert run.returncode == 0, run.stderr[-2000:]
    ckpt = str(tmp_path / "run" / "latest.pt")
    ev = _cli(site, "cli", "eval", ckpt, str(tiny_ds), "--late-fusion", "--conf", "0.05", "--out", str(tmp_path / "ev"))
    assert ev.returncode == 0, ev.stderr[-2000:]
    comparison = json.loads((tmp_path / "ev" / "comparison.json").read_text())["models"]
    assert set(comparison) == {"ground-mean", "ground-mean, late fusion"}
    assert comparison["ground-mean, late fusion"]["bytes_per_car_frame"] > 0  # each car sent its 3D detections
    assert comparison["ground-mean"]["3d"] is not None  # world outputs: the ground-plane metrics apply
    exp = _cli(site, "cli.export", ckpt, "--onnx", str(tmp_path / "gm.onnx"), "--size", "64x48")
    assert exp.returncode == 0, exp.stderr[-2000:]
    pred = {}
    for backend in ("torch", "onnxruntime"):
        extra = ["--backend", "onnxruntime", "--onnx", str(tmp_path / "gm.onnx")] if backend != "torch" else []
        res = _cli(site, "cli", "predict", ckpt, str(tiny_ds), "--split", "train", "--conf", "0.05", "--quiet",
                   "--out", str(tmp_path / backend), *extra)
        assert res.returncode == 0, res.stderr[-2000:]
        pred[backend] = json.loads((tmp_path / backend / "results_train.json").read_text())
    assert len(pred["torch"]) == len(pred["onnxruntime"])
    assert all(abs(a["score"] - b["score"]) < 1e-4 for a, b in zip(pred["torch"], pred["onnxruntime"]))


def test_the_guide_shows_the_example_kind_word_for_word():
    """docs/guide/detector.md's "Write your own model" holds tests/example_kind's module and its entry point."""
    guide = (ROOT / "docs" / "guide" / "detector.md").read_text()
    code = (ROOT / "tests" / "example_kind" / "ground_mean_kind.py").read_text()
    assert code.strip() in guide
    toml = (ROOT / "tests" / "example_kind" / "pyproject.toml").read_text()
    assert '[project.entry-points."pnyolo.models"]\nground-mean = "ground_mean_kind:GroundMean"' in toml
    assert '[project.entry-points."pnyolo.models"]\nground-mean = "ground_mean_kind:GroundMean"' in guide


def test_a_yolo_grid_kind_without_registered_anchors_is_refused_when_built():
    from dataset_spec.cli_support import UserError

    class NoAnchors(TinyExample):
        def __init__(self, cfg, num_classes: int):
            YoloGridModel.__init__(self, cfg, num_classes)  # forgets self.register_buffer("anchors", ...)

    register_model("no-anchors")(NoAnchors)
    try:
        with pytest.raises(UserError, match="registers its anchors in __init__"):
            build_model(load_config(None, ["model.kind=no-anchors"]), 2)
    finally:
        unregister_model("no-anchors")
