"""Predict once, analyse many (issue 77): the models run in one place (``pnyolo.engine.predict``); every
analysis reads predictions. The rule is checked on the code (no analysis module can reach a model) and on a run
(scoring, late fusion, the sweeps and tracking make no forward pass)."""
from __future__ import annotations

import ast
import dataclasses
import importlib
from pathlib import Path

import numpy as np
import pytest
import torch
from test_pnyolo_common import TINY, for_kind, make_dataset

from pnyolo.config import load_config
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.models import build_model
from repo_paths import REPO

ROOT = REPO / "pnyolo"
ANALYSES = ("evaluation", "cooperation", "tracking")  # packages that read predictions only
BENCH_ANALYSES = ("late_choice.py", "robustness.py", "time_axis.py", "report.py", "targets.py", "record.py")
MODEL_CALLS = {"predict_item", "predict", "predict_plan", "predict_scoring", "time_per_item", "forward", "rig_constants_on_device"}


def _analysis_modules() -> list[Path]:
    return sorted([f for p in ANALYSES for f in (ROOT / p).rglob("*.py")] + [ROOT / "bench" / n for n in BENCH_ANALYSES])


def _model_reach(path: Path) -> list[str]:
    """What in ``path`` could run a model: an import from pnyolo.engine or of ``predict_item`` (and the like), or a
    call of such a name or of a ``forward`` method; an import for type checking only is never run."""
    found, tree = [], ast.parse(path.read_text())
    typing_only = {id(n) for block in ast.walk(tree) if isinstance(block, ast.If)
                   and isinstance(block.test, ast.Name) and block.test.id == "TYPE_CHECKING" for n in ast.walk(block)}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and id(node) not in typing_only:
            names = {a.name for a in node.names}
            if node.module.startswith("pnyolo.engine") or names & MODEL_CALLS:
                found.append(f"line {node.lineno}: from {node.module} import {', '.join(sorted(names))}")
        elif isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
            if name in MODEL_CALLS:
                found.append(f"line {node.lineno}: calls {name}")
    return found


def test_no_analysis_module_can_run_a_model():
    """The scoring, the cars' protocol, tracking and the bench's analyses import nothing that runs a model."""
    modules = _analysis_modules()
    assert len(modules) > 30
    bad = {str(m.relative_to(ROOT)): r for m in modules if (r := _model_reach(m))}
    assert not bad, bad


def test_the_check_finds_a_model_call_where_there_is_one(tmp_path):
    """The rule above can fail: a module that calls predict_item, or forwards a model itself, is caught."""
    calls = tmp_path / "calls.py"
    calls.write_text("from pnyolo.models import predict_item\n\ndef f(m, x):\n    return m.forward(x)\n")
    assert len(_model_reach(calls)) == 2
    typed = tmp_path / "typed.py"
    typed.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pnyolo.engine.predict import Predictions\n"
                     "from pnyolo.engine.predict import predict\n")
    assert _model_reach(typed) == ["line 4: from pnyolo.engine.predict import predict"]  # the type alone passes
    assert len(_model_reach(ROOT / "engine" / "predict.py")) > 0  # the one place that does


def test_predict_item_is_called_only_in_engine_and_the_models():
    """Outside training, prediction and the model kinds themselves, nothing names predict_item."""
    users = sorted(str(f.relative_to(ROOT)) for f in ROOT.rglob("*.py") if "predict_item" in f.read_text())
    assert all(u.startswith(("engine/", "training/", "models/", "onnx/")) for u in users), users


@pytest.fixture(scope="module")
def bev(tmp_path_factory):
    root = make_dataset(tmp_path_factory.mktemp("once") / "ds", n_scenarios=2)
    cfg = load_config(None, for_kind(TINY, ["model.kind=bev", "eval.conf_threshold=0.02"]))
    torch.manual_seed(0)
    return root, cfg, build_model(cfg, 2).eval()


def test_scoring_late_fusion_and_pose_noise_make_no_forward_pass(bev, monkeypatch):
    """Predicted once, a comparison with the own-view ablation, late fusion (into an ego too) and pose noise in
    the channel is scored without a single forward; predicting makes one per item and condition."""
    import pnyolo.engine.predict as engine
    from pnyolo.cooperation.late_fusion import Channel
    from pnyolo.cooperation.pose_noise import PoseNoise
    from pnyolo.bench.plan import predict_scoring
    from pnyolo.engine.predict import Trained
    from pnyolo.evaluation.evaluate import Comparison, LateInto, evaluate_models

    root, cfg, model = bev
    ds = MultiViewDataset(root, "test", cfg, every_camera=True)
    calls = []
    real = engine.predict_item
    monkeypatch.setattr(engine, "predict_item", lambda *a, **k: calls.append(1) or real(*a, **k))
    scoring = predict_scoring(Trained(None, model, cfg), ds, own=True)
    assert len(calls) == 2 * len(ds)  # clean and own view, once each
    monkeypatch.setattr(engine, "predict_item", lambda *a, **k: pytest.fail("a forward pass while scoring"))
    for channel in (Channel(), Channel(PoseNoise(0.3, 0.3, 0))):
        plan = Comparison({"bev": scoring, "ego": scoring}, own_view=("bev",), late=("bev",), channel=channel,
                          late_into=LateInto("bev", "ego", 0.05, 0.05))
        accs = evaluate_models(plan, ds)
        assert len(accs) == 5 and all(a.summary()["views"] > 0 for a in accs.values())


def test_decoding_fewer_depth_peaks_from_more_is_a_pass_with_fewer(tmp_path):
    """Each decoding setting is applied to stored outputs: outputs kept at 3 depth peaks decode at 1 and 2 exactly
    as passes with 1 and 2 do (the peaks are found one after another)."""
    from pnyolo.engine.predict import Condition, predict

    root = make_dataset(tmp_path / "ds", n_scenarios=1)
    cfg = load_config(None, [*TINY, "eval.conf_threshold=0.0"])
    torch.manual_seed(0)
    model = build_model(cfg, 2).eval()
    ds = MultiViewDataset(root, "train", cfg, views=[0, 1, 2])
    most = predict(model, ds, cfg.eval, Condition(peaks=3))
    for k in (1, 2):
        ev = dataclasses.replace(cfg.eval, depth_peaks=k)
        one = predict(model, ds, ev)
        for i in range(len(ds)):
            a, b = most.detections_at(i, ev), one.detections_at(i, ev)
            assert sum(len(d.scores) for d in a) > 0
            for x, y in zip(a, b):
                assert np.array_equal(x.boxes, y.boxes) and np.array_equal(x.scores, y.scores)


def test_predictions_of_a_subset_dataset_are_the_whole_ones_items(bev):
    """A dataset of some of the items (a later first frame, fewer lightings) reads the whole one's predictions."""
    from pnyolo.engine.predict import predict

    root, cfg, model = bev
    whole = MultiViewDataset(root, "test", cfg, every_camera=True)
    preds = predict(model, whole, cfg.eval)
    one_light = MultiViewDataset(root, "test", dataclasses.replace(
        cfg, data=dataclasses.replace(cfg.data, variants=["dusk"])), every_camera=True)
    sub = preds.on(one_light)
    assert 0 < len(sub) < len(preds) and all(p.item.variant == "dusk" for p in sub.items)
    for k, p in enumerate(sub.items):
        assert p is preds.items[list(map(str, preds.keys)).index(str(one_light.items[k]))]


def test_the_prediction_door_hands_out_the_kinds_decoding_not_the_model(bev):
    """Issue 86, item 3: what an analysis gets from predictions decodes (the same detections as the model's own
    decode) but holds no forward pass, parameters or mode to change; the door's fields are typed."""
    import typing

    from pnyolo.engine.predict import Predicted, Predictions, Trained, predict
    from pnyolo.evaluation.evaluate import Scoring
    from pnyolo.models import Decoding

    root, cfg, model = bev
    ds = MultiViewDataset(root, "test", cfg, every_camera=True)
    preds = predict(model, ds, cfg.eval)
    door = preds.decoding
    assert isinstance(door, Decoding) and not hasattr(preds, "model")
    assert not any(hasattr(door, n) for n in ("forward", "parameters", "train", "eval", "state_dict", "model"))
    for k, p in enumerate(preds.items):
        mine, theirs = preds.detections_at(k, cfg.eval), model.decode(p.out, p.item, cfg.eval)
        assert all(np.array_equal(a.boxes, b.boxes) and np.array_equal(a.scores, b.scores) for a, b in zip(mine, theirs))
    assert (door.kind, door.world_outputs, door.reads_other_views) == ("bev", True, True)
    with pytest.raises(dataclasses.FrozenInstanceError):
        door.world_outputs = False
    for cls in (Trained, Predicted, Predictions, Scoring):
        hints = typing.get_type_hints(cls, vars(importlib.import_module(cls.__module__)) | {"Predictions": Predictions})
        assert object not in hints.values(), (cls.__name__, hints)
