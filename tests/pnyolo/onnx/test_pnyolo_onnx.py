"""Every model kind exported to ONNX and run by ONNX Runtime gives the torch backend's outputs and
detections; a file of another checkpoint, or a call with other views or sizes, is refused in one line."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from test_pnyolo_common import TINY, make_dataset, tiny

from pnyolo.cli import train_main
from pnyolo.config import load_config
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.cli.export import main as export_main
from pnyolo.models import build_model, predict_item
from pnyolo.cli.predict import main as predict_main

pytest.importorskip("onnxruntime")
from pnyolo.onnx.backend import OnnxRunner, export_onnx  # noqa: E402

KINDS = {"single-view": [], "bev": ["model.bev.range_m=30"],
         # fine samples and depth peaks: the steps that needed ONNX-friendly forms (no searchsorted, cumprod)
         "pixelnerf-yolo": ["model.sampler.fine_samples=4", "eval.depth_peaks=2", "eval.depth_gap=4.0"]}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("onnx") / "ds", n_scenarios=1)


def _flat(out) -> dict[str, torch.Tensor]:
    from pnyolo.models.yolo_grid import flatten_outputs

    return flatten_outputs(out) if hasattr(out, "ray_confidence") else {"heatmap": out.heatmap, "regression": out.regression}


@pytest.mark.parametrize("kind", list(KINDS))
def test_onnx_runtime_gives_the_torch_outputs_and_detections(kind, dataset, tmp_path):
    torch.manual_seed(0)
    cfg = load_config(None, tiny(f"model.kind={kind}", *KINDS[kind]))
    model = build_model(cfg, 2).eval()
    with torch.no_grad():  # spread the untrained scores: no near-ties for NMS to break either way
        for p in model.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    item = MultiViewDataset(dataset, "train", cfg, training=False)[0]
    h, w = item.images.shape[-2:]
    path = export_onnx(model, tmp_path / "m.onnx", w, h, len(item.images), cfg.eval)
    with torch.no_grad():
        ours = predict_item(model, item, "cpu", cfg.eval)
    theirs = OnnxRunner(path, model, threads=1)(item)
    a, b = _flat(ours), _flat(theirs)
    assert set(a) == set(b) and len(a) >= 2
    for name in a:
        assert a[name].shape == b[name].shape
        assert torch.allclose(a[name].nan_to_num(), b[name].nan_to_num(), atol=1e-4, rtol=0), name
    cfg = replace(cfg, eval=replace(cfg.eval, conf_threshold=0.0))  # every candidate: the same boxes survive NMS
    da, db = model.decode(ours, item, cfg.eval), model.decode(theirs, item, cfg.eval)
    assert sum(len(x.boxes) for x in da) > 0
    for x, y in zip(da, db):
        assert len(x.boxes) == len(y.boxes)
        assert np.allclose(x.scores, y.scores, atol=1e-4) and np.allclose(x.boxes, y.boxes, atol=1e-3)


def test_a_file_of_another_checkpoint_or_size_is_refused(dataset, tmp_path):
    torch.manual_seed(0)
    cfg = load_config(None, tiny("model.kind=single-view"))
    model = build_model(cfg, 2).eval()
    item = MultiViewDataset(dataset, "train", cfg, training=False)[0]
    h, w = item.images.shape[-2:]
    path = export_onnx(model, tmp_path / "m.onnx", w, h, len(item.images), cfg.eval)
    other = build_model(cfg, 2).eval()  # the same config, other weights
    with pytest.raises(Exception, match="weights differs"):
        OnnxRunner(path, other)
    small = export_onnx(model, tmp_path / "small.onnx", w // 2, h // 2, len(item.images), cfg.eval)
    with pytest.raises(Exception, match="exported for 3 views of 32x24"):
        OnnxRunner(small, model)(item)


def test_export_and_predict_commands_round_trip(dataset, tmp_path, capsys):
    sets = sum((["--set", s] for s in [*TINY, "train.max_steps=2", "train.epochs=1"]), [])
    assert train_main([str(dataset), "--out", str(tmp_path / "run"), "--quiet", *sets]) == 0
    ckpt = str(tmp_path / "run" / "latest.pt")
    import warnings

    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        assert export_main([ckpt, "--onnx", str(tmp_path / "m.onnx"), "--size", "64x48"]) == 0
    assert not [w for w in said if issubclass(w.category, (torch.jit.TracerWarning, DeprecationWarning))], \
        [str(w.message)[:80] for w in said]
    assert "pixelnerf-yolo for 3 views of 64x48" in capsys.readouterr().out
    for backend in ("torch", "onnxruntime"):
        extra = ["--backend", "onnxruntime", "--onnx", str(tmp_path / "m.onnx")] if backend != "torch" else []
        assert predict_main([ckpt, str(dataset), "--split", "train", "--conf", "0.01", "--out",
                             str(tmp_path / backend), "--quiet", *extra]) == 0
    rows = {b: json.loads((tmp_path / b / "results_train.json").read_text()) for b in ("torch", "onnxruntime")}
    assert len(rows["torch"]) == len(rows["onnxruntime"]) > 0
    same = 0
    for r, s in zip(rows["torch"], rows["onnxruntime"]):
        assert r["image_id"] == s["image_id"] and abs(r["score"] - s["score"]) < 1e-4
        same += np.allclose(r["bbox"], s["bbox"], atol=1e-2)
    assert same >= 0.95 * len(rows["torch"])  # a 2-step model's near-equal scores may let NMS keep the twin
    # the Python API: Detector.load with the ONNX backend answers as the torch one
    from dataset_spec import Dataset
    from pnyolo.inference import Detector

    ds = Dataset.open(dataset)
    scn = ds.scenario(ds.scenario_names()[0])
    cams = scn.cameras[:3]
    images = [ds.read_rgb(scn.name, c.name, scn.lighting[0].name) for c in cams]
    a = Detector.load(ckpt).detect(images, cams, conf_threshold=0.01)
    b = Detector.load(ckpt, backend="onnxruntime", onnx=tmp_path / "m.onnx", threads=1).detect(images, cams,
                                                                                                  conf_threshold=0.01)
    assert [len(v) for v in a] == [len(v) for v in b] and sum(len(v) for v in a) > 0
    assert all(abs(x.score - y.score) < 1e-4 for u, w in zip(a, b) for x, y in zip(u, w))
    capsys.readouterr()
    assert export_main([ckpt, "--onnx", str(tmp_path / "x.onnx"), "--size", "64by48"]) == 2
    assert "--size '64by48'" in capsys.readouterr().err
    assert predict_main([ckpt, str(dataset), "--backend", "onnxruntime", "--out", str(tmp_path / "p")]) == 2
    assert "go together" in capsys.readouterr().err
