"""INT8 ONNX files (QDQ, calibrated on a dataset's frames): every kind's quantised graph runs in ONNX Runtime
with outputs that follow FP32's, keeps the export's metadata, and bad calibration input is one line."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from test_pnyolo_common import TINY, make_dataset, tiny

from pnyolo.cli import train_main
from pnyolo.config import load_config
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.cli.export import main as export_main
from pnyolo.models import build_model

pytest.importorskip("onnxruntime")
from pnyolo.onnx.backend import OnnxRunner, export_onnx  # noqa: E402
from pnyolo.onnx.int8 import geometry_nodes, quantize_int8  # noqa: E402

KINDS = {"single-view": ("confidence", []), "bev": ("heatmap", ["model.bev.range_m=30"]),
         "pixelnerf-yolo": ("confidence", [])}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("int8") / "ds", n_scenarios=3)


@pytest.mark.parametrize("kind", list(KINDS))
def test_an_int8_graph_follows_the_fp32_one(kind, dataset, tmp_path):
    import onnx

    key, extra = KINDS[kind]
    torch.manual_seed(0)
    cfg = load_config(None, tiny(f"model.kind={kind}", *extra))
    model = build_model(cfg, 2).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    data = MultiViewDataset(dataset, "train", cfg, training=False)
    item = data[0]
    h, w = item.images.shape[-2:]
    fp32 = export_onnx(model, tmp_path / "m.onnx", w, h, len(item.images), cfg.eval)
    int8 = quantize_int8(model, fp32, tmp_path / "m_int8.onnx", [data[k] for k in range(len(data))])
    meta = {p.key: p.value for p in onnx.load(str(int8)).metadata_props}
    assert meta["pnyolo.precision"] == "int8" and meta["pnyolo.kind"] == kind
    graph = onnx.load(str(int8)).graph
    assert any(n.op_type == "QuantizeLinear" for n in graph.node)
    # the cameras' arithmetic stays FP32: no activation computed from K, camera_to_world or points alone is
    # quantised, and no product of two activations (a projection by the input cameras) is
    source = onnx.load(str(fp32)).graph
    geometry = {o for n in source.node if n.name in geometry_nodes(source) for o in n.output}
    geometry |= {i.name for i in source.input if i.name != "images"}
    assert (kind == "single-view" or geometry) and not {n.input[0] for n in graph.node if n.op_type == "QuantizeLinear"} & geometry
    weights = {i.name for i in graph.initializer}
    made = {o: n for n in graph.node for o in n.output}
    for n in graph.node:
        if n.op_type in ("Conv", "MatMul", "Gemm") and made.get(n.input[0], n).op_type == "DequantizeLinear":
            producer = made.get(n.input[1])
            assert producer is not None and producer.op_type == "DequantizeLinear" and producer.input[0] in weights, n.name
    a, b = OnnxRunner(fp32, model, threads=1)(item), OnnxRunner(int8, model, threads=1)(item)
    from test_pnyolo_onnx import _flat

    x, y = _flat(a)[key].flatten().numpy(), _flat(b)[key].flatten().numpy()
    assert np.corrcoef(x, y)[0, 1] > 0.85, key  # random weights: the quantised graph still tracks FP32's


def test_int8_export_from_the_command_and_its_bad_input(dataset, tmp_path, capsys):
    sets = sum((["--set", s] for s in tiny("model.kind=single-view", "train.max_steps=1", "train.epochs=1")), [])
    assert train_main([str(dataset), "--out", str(tmp_path / "run"), "--quiet", *sets]) == 0
    ckpt = str(tmp_path / "run" / "latest.pt")
    assert export_main([ckpt, "--onnx", str(tmp_path / "q.onnx"), "--size", "64x48", "--int8", "--calibrate",
                        str(dataset), "--split", "train", "--calibration-frames", "2"]) == 0
    assert "INT8 (calibrated on 2 frames)" in capsys.readouterr().out
    other = make_dataset(tmp_path / "big", n_scenarios=1, width=80, height=48)
    shutil.copytree(dataset, tmp_path / "cars")
    info = json.loads((tmp_path / "cars" / "dataset.json").read_text())
    info["classes"][1]["detectable"] = False  # cars only
    (tmp_path / "cars" / "dataset.json").write_text(json.dumps(info))
    for args, words in ((["--int8"], "go together"), (["--calibrate", str(dataset)], "go together"),
                        (["--int8", "--calibrate", str(dataset), "--split", "nope"], "invalid choice: 'nope'"),
                        (["--int8", "--calibrate", str(other), "--split", "train"], "the export is for 64x48"),
                        (["--int8", "--calibrate", str(tmp_path / "cars"), "--split", "train"], "not the checkpoint's")):
        try:
            rc = export_main([ckpt, "--onnx", str(tmp_path / "x.onnx"), "--size", "64x48", *args])
        except SystemExit as exc:  # argparse's own refusal (a split name that is no split)
            rc = exc.code
        assert rc != 0
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], err
    assert not (tmp_path / "x.onnx").exists()
