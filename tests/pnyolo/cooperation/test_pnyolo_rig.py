"""A rig that does not move: what depends only on its cameras is computed once (``Detector.for_rig``,
and ``pnyolo-predict`` for the frames of a parked rig), with the very outputs of the path without it;
frames from cameras that moved are refused in one line."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from test_pnyolo_common import tiny
from test_pnyolo_common import smooth_frame

from dataset_spec.cli_support import UserError
from pnyolo.config import load_config
from pnyolo.data.frame import frame_item
from pnyolo.inference import Detector, RigConstants
from pnyolo.models import build_model, predict_item

KINDS = {"single-view": [], "bev": ["model.bev.range_m=30"], "pixelnerf-yolo": []}


@pytest.mark.parametrize("kind", list(KINDS))
def test_the_rig_s_constants_give_bit_identical_outputs_and_moved_cameras_are_refused(kind):
    torch.manual_seed(0)
    cfg = load_config(None, tiny(f"model.kind={kind}", "eval.conf_threshold=0.01", *KINDS[kind]))
    model = build_model(cfg, 2).eval()
    images, K, c2w = smooth_frame()
    cams = list(zip(K, c2w))
    det = Detector(model, cfg, ["car", "pedestrian"])
    rig = det.for_rig(cams, images.shape[2], images.shape[1])
    if kind == "bev":  # the grid and its pillars' pixels: computed once
        assert set(rig.constants) == {"bev_grid", "projection"}
    item, _ = frame_item(list(images), cams, cfg.data, ["car", "pedestrian"])
    with torch.no_grad():
        plain = predict_item(model, item, "cpu", cfg.eval)
        cached = predict_item(model, item, "cpu", cfg.eval, **RigConstants(model)(item))
    for name in ("heatmap", "regression") if kind == "bev" else ("ray_confidence", "box", "class_logits"):
        assert torch.equal(getattr(plain, name), getattr(cached, name)), name
    for frame in range(2):  # frame after frame, the detections of the uncached path
        shown = [np.roll(im, 8 * frame, axis=1) for im in images]
        a, b = det.detect(shown, cams), rig.detect(shown)
        assert [[(d.class_index, d.score, d.box.tolist()) for d in v] for v in a] == \
               [[(d.class_index, d.score, d.box.tolist()) for d in v] for v in b]
    moved = [(k, c.copy()) for k, c in cams]
    moved[1][1][0, 3] += 0.5
    with pytest.raises(UserError, match="not the rig's"):
        rig.detect(list(images), moved)
    with pytest.raises(UserError, match="set up for 64x48"):
        rig.detect([im[:, :32] for im in images])


def test_the_cache_follows_cameras_that_move():
    torch.manual_seed(0)
    cfg = load_config(None, tiny("model.kind=bev", "model.bev.range_m=30"))
    model = build_model(cfg, 2).eval()
    images, K, c2w = smooth_frame()
    cache = RigConstants(model)
    first = cache(frame_item(list(images), list(zip(K, c2w)), cfg.data, ["car", "pedestrian"])[0])
    assert cache(frame_item(list(images), list(zip(K, c2w)), cfg.data, ["car", "pedestrian"])[0]) is first
    c2w = c2w.copy()
    c2w[:, 0, 3] += 3.0  # the rig drove on
    item = frame_item(list(images), list(zip(K, c2w)), cfg.data, ["car", "pedestrian"])[0]
    moved = cache(item)
    assert moved is not first and moved["bev_grid"] != first["bev_grid"]
    with torch.no_grad():
        assert torch.equal(predict_item(model, item, "cpu", cfg.eval, **moved).heatmap,
                           predict_item(model, item, "cpu", cfg.eval).heatmap)
