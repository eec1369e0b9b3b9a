"""pixelNeRF-YOLO as a kind with 3D detections (issue 89): each view's detections are world boxes, a road user two
views report is one after pooling (late fusion's and the ground plane's rule), and a model trained without the 3D
state says so in one line wherever 3D detections are asked of it."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_pnyolo_common import tiny

from dataset_spec.cli_support import UserError
from pnyolo.components.renderer import RayOutputs
from pnyolo.components.view_state import STATE, state_targets
from pnyolo.config import load_config
from pnyolo.cooperation.late_fusion import check_late_fusion, pool_cars
from pnyolo.data.frame import frame_item
from pnyolo.decoding.world import pool_views
from pnyolo.models import Decoding, build_model
from pnyolo.registry import model_class

CAR = np.array([12.0, 3.0, 1.2, 4.4, 1.8, 1.5, 2.2])  # x, y, z, length, width, height, yaw
ROW, COL, ANCHOR = 3, 4, 1  # the cell both views see the car in (8 x 6 cells of 8 px on a 64 x 48 image)


def _looking_at(target: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """K with its principal point on cell (ROW, COL)'s centre, and a level OpenCV camera at ``at`` facing ``target``."""
    u, v = (COL + 0.5) / 8 * 64 - 0.5, (ROW + 0.5) / 6 * 48 - 0.5
    K = np.array([[60.0, 0, u], [0, 60.0, v], [0, 0, 1]])
    forward = (target - at) / np.linalg.norm(target - at)
    right = np.array([forward[1], -forward[0], 0.0]) / math.hypot(forward[0], forward[1])
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, np.cross(forward, right), forward], axis=1)
    c2w[:3, 3] = at
    return K, c2w


def _two_views_see_the_car(state: bool = True):
    """A tiny pixelNeRF-YOLO, an item of two cars' cameras looking at CAR from either side, and outputs in which both
    views report it in cell (ROW, COL) at its distance with its state."""
    cfg = load_config(None, tiny("model.kind=pixelnerf-yolo", f"model.loss.state={1.0 if state else 0.0}"))
    model = build_model(cfg, 2).eval()
    cameras = [_looking_at(CAR[:3], np.array([0.0, 0.0, 1.2])), _looking_at(CAR[:3], np.array([20.0, 14.0, 1.2]))]
    item, _ = frame_item([np.zeros((48, 64, 3), np.uint8)] * 2, cameras, cfg.data, ["car", "pedestrian"])
    assert (item.grid.grid_w, item.grid.grid_h, item.grid.width) == (8, 6, 64)
    shape = (2, 6, 8, 3)
    conf, depth, logits = torch.zeros(shape), torch.zeros(shape), torch.zeros(*shape, 2)
    values = torch.zeros(*shape, len(STATE) if state else 0)
    for v, (_, c2w) in enumerate(cameras):
        conf[v, ROW, COL, ANCHOR] = 0.9
        depth[v, ROW, COL, ANCHOR] = float(np.linalg.norm(CAR[:3] - c2w[:3, 3]))
        logits[v, ROW, COL, ANCHOR, 0] = 5.0  # a car
        if state:
            values[v, ROW, COL, ANCHOR] = state_targets(torch.tensor(CAR)[None], torch.tensor(c2w[:3, 3])[None])[0]
            values[v, ROW, COL, ANCHOR, -1] *= 10  # the front as a confident logit
    return model, item, RayOutputs(conf, torch.zeros(*shape, 4), logits, depth, state=values), cfg.eval


def test_each_view_reports_the_road_user_it_sees_as_its_world_box():
    model, item, out, ev = _two_views_see_the_car()
    assert model.world_outputs and model_class("pixelnerf-yolo").world_outputs
    check_late_fusion(Decoding.of(model))  # accepted
    reports = model.world_detections(out, item, ev, 0.5)
    assert len(reports) == 2  # one entry per view
    for r in reports:
        assert len(r) == 1 and int(r.classes[0]) == 0
        np.testing.assert_allclose(r.boxes[0, :6], CAR[:6], atol=1e-4)
        assert abs(math.remainder(r.boxes[0, 6] - CAR[6], 2 * math.pi)) < 1e-4
    assert all(len(r) == 0 for r in model.world_detections(out, item, ev, 0.95))  # the threshold applies


def test_a_road_user_two_views_report_is_one_after_pooling():
    model, item, out, ev = _two_views_see_the_car()
    reports = model.world_detections(out, item, ev, 0.5)
    pooled = pool_views(reports, ev.centre_nms_m)  # the ground plane's rule
    assert len(pooled) == 1
    np.testing.assert_allclose(pooled.boxes[0, :3], CAR[:3], atol=1e-4)
    assert len(pool_cars(reports, [0, 1], ev.centre_nms_m, None)) == 1  # late fusion's and the tracker's
    moved = [reports[0], reports[1].take(np.array([0]))]
    moved[1].boxes[:, 0] += 3 * ev.centre_nms_m  # reported far apart: two road users
    assert len(pool_views(moved, ev.centre_nms_m)) == 2
    alone = pool_views([reports[0]], ev.centre_nms_m)  # one part: as its kind merged it
    assert np.array_equal(alone.boxes, reports[0].boxes) and np.array_equal(alone.scores, reports[0].scores)


def test_a_model_trained_without_the_state_has_no_3d_detections_and_says_why():
    model, item, out, ev = _two_views_see_the_car(state=False)
    assert not model.world_outputs  # the built model, whatever its kind can do
    with pytest.raises(UserError, match=r"model.loss.state 0"):
        check_late_fusion(Decoding.of(model))
    with pytest.raises(UserError, match=r"no 3D state"):
        model.world_detections(out, item, ev, 0.5)
