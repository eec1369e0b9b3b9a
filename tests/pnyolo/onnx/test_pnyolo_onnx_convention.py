"""An exported graph called from outside the project: a process that imports only numpy, OpenCV and
ONNX Runtime builds the inputs and decodes the outputs from the file's documented calling convention
(``pnyolo.convention``, tests/onnx_client.py) to the detections the project's own decoding gives."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from test_pnyolo_common import smooth_frame, tiny

from pnyolo.config import load_config
from pnyolo.data.frame import frame_item
from pnyolo.models import build_model, predict_item

pytest.importorskip("onnxruntime")
from pnyolo.onnx.backend import export_onnx  # noqa: E402
from repo_paths import TESTS

KINDS = {"single-view": [], "bev": ["model.bev.range_m=30", "eval.conf_threshold=0.002"], "pixelnerf-yolo": ["eval.depth_gap=4.0"]}
CLIENT = TESTS / "onnx_client.py"


@pytest.mark.parametrize("kind", list(KINDS))
def test_a_caller_outside_the_project_decodes_the_documented_outputs(kind, tmp_path):
    torch.manual_seed(0)
    cfg = load_config(None, tiny(f"model.kind={kind}", "eval.conf_threshold=0.1", *KINDS[kind]))
    model = build_model(cfg, 2).eval()
    with torch.no_grad():  # spread the untrained scores: no near-ties for NMS to break either way
        for p in model.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    images, K, c2w = smooth_frame()
    item, _ = frame_item(list(images), list(zip(K, c2w)), cfg.data, ["car", "pedestrian"])
    with torch.no_grad():
        out = predict_item(model, item, "cpu", cfg.eval)
    if kind != "bev":  # a threshold between the 20th and 21st score: candidates to decode whatever the draw gave
        top = out.ray_confidence.flatten().sort(descending=True).values[19:21].tolist()
        cfg = load_config(None, tiny(f"model.kind={kind}", f"eval.conf_threshold={sum(top) / 2}", *KINDS[kind]))
    path = export_onnx(model, tmp_path / "m.onnx", images.shape[2], images.shape[1], len(images), cfg.eval,
                       ["car", "pedestrian"])
    np.savez(tmp_path / "frame.npz", images=images, K=K, camera_to_world=c2w)  # bev: the grid from its rule
    subprocess.run([sys.executable, "-I", str(CLIENT), str(path), str(tmp_path / "frame.npz"),
                    str(tmp_path / "dets.json")], check=True)
    theirs = json.loads((tmp_path / "dets.json").read_text())
    assert theirs["imported"] == []  # numpy, OpenCV and ONNX Runtime only
    assert "depth" not in theirs["outputs"] or model.estimates_depth  # no output that is all NaN
    if kind == "bev":
        ours = model.world_detections(out, item, cfg.eval, cfg.eval.conf_threshold)[0]
        got = theirs["detections"]
        assert len(ours.boxes) > 0 and len(got) == len(ours.boxes)
        assert np.allclose([d["box"] for d in got], ours.boxes, atol=1e-3)
        assert np.allclose([d["score"] for d in got], ours.scores, atol=1e-4)
        assert [d["class"] for d in got] == ours.classes.tolist()
        return
    ours = model.decode(out, item, cfg.eval)
    assert sum(len(d.boxes) for d in ours) > 0
    for d, got in zip(ours, theirs["detections"]):
        assert len(got["boxes"]) == len(d.boxes)
        assert np.allclose(np.reshape(got["boxes"], (-1, 4)), d.boxes, atol=1e-3)
        assert np.allclose(got["scores"], d.scores, atol=1e-4) and got["classes"] == d.classes.tolist()
        assert ("world_boxes" in got) == (d.world_boxes is not None) == (kind == "pixelnerf-yolo")
        if d.world_boxes is not None:  # the 3D state decoded by the convention's words alone
            theirs_3d = np.reshape(got["world_boxes"], (-1, 7))
            assert np.allclose(theirs_3d[:, :6], d.world_boxes[:, :6], atol=1e-3)
            assert np.allclose(np.remainder(theirs_3d[:, 6] - d.world_boxes[:, 6] + np.pi, 2 * np.pi), np.pi, atol=1e-3)
