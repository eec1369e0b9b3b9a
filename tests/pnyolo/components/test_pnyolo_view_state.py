"""pixelNeRF-YOLO's 3D state (pnyolo.components.view_state): a detection at its distance with its state is the world box
it was made from; the state's targets and loss; the state changes none of the YOLO outputs."""
from __future__ import annotations

import math

import numpy as np
import torch
from test_pnyolo_common import smooth_frame, tiny

from dataset_spec.camera import pixel_rays
from pnyolo.components.heading import heading_encoding, heading_targets
from pnyolo.components.renderer import RayOutputs
from pnyolo.components.view_state import STATE, state_targets, view_state_loss, world_boxes
from pnyolo.config import load_config
from pnyolo.data.grid import GridSpec
from pnyolo.data.targets import OBJECT, TARGET_CHANNELS
from pnyolo.decoding.yolo import decode_outputs
from pnyolo.models import build_model, predict_item
from pnyolo.data.frame import frame_item


def _camera(yaw: float, at=(3.0, -2.0, 1.5)) -> tuple[np.ndarray, np.ndarray]:
    """K and an OpenCV camera_to_world looking level along world heading ``yaw`` from ``at``."""
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    forward = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, np.cross(forward, right), forward], axis=1)  # x right, y down, z forward
    c2w[:3, 3] = at
    return K, c2w


def test_a_detection_at_a_known_distance_with_its_state_decodes_to_the_box_it_came_from():
    K, c2w = _camera(0.4)
    grid = GridSpec(64, 48, 8, 6)
    row, col, a, distance = 2, 5, 1, 11.0
    u, v = (col + 0.5) / grid.grid_w * grid.width - 0.5, (row + 0.5) / grid.grid_h * grid.height - 0.5
    origin, direction = pixel_rays(K, c2w, np.array([u, v]))
    box = np.array([*(origin + direction * distance), 4.4, 1.8, 1.5, 2.9])  # a car on the cell's ray, facing back
    shape = (1, grid.grid_h, grid.grid_w, 3)
    conf, depth = torch.zeros(shape), torch.zeros(shape)
    conf[0, row, col, a], depth[0, row, col, a] = 0.9, distance
    state = torch.zeros(*shape, len(STATE))
    state[0, row, col, a] = state_targets(torch.tensor(box)[None], torch.tensor(c2w[:3, 3])[None])[0]
    state[0, row, col, a, -1] *= 10  # the front as a confident logit
    out = RayOutputs(conf, torch.zeros(*shape, 4), torch.zeros(*shape, 2), depth, state=state)
    anchors = torch.tensor([[0.1, 0.1], [0.2, 0.2], [0.3, 0.3]])
    det = decode_outputs(out, anchors, grid, 0.5, 0.5, None, [(K, c2w)])[0]
    assert len(det.boxes) == 1
    np.testing.assert_allclose(det.world_boxes[0, :6], box[:6], atol=1e-5)
    assert abs(math.remainder(det.world_boxes[0, 6] - box[6], 2 * math.pi)) < 1e-5
    assert decode_outputs(out, anchors, grid, 0.5, 0.5)[0].world_boxes is None  # no cameras: pixels only


def test_the_state_of_a_road_user_depends_on_how_the_camera_sees_it_not_on_where_the_scene_is_turned():
    box, origin = torch.tensor([[10.0, 4.0, 0.8, 4.4, 1.8, 1.5, 0.7]]), torch.tensor([[1.0, -1.0, 1.4]])
    for turn in (0.5, 2.0, -2.6):  # the camera and the car turned together about the world's z axis
        c, s = math.cos(turn), math.sin(turn)
        R = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        turned = torch.cat([box[:, :3] @ R.T, box[:, 3:6], box[:, 6:] + turn], dim=1)
        torch.testing.assert_close(state_targets(turned, origin @ R.T), state_targets(box, origin), atol=1e-5, rtol=0)
    moved = box.clone()
    moved[0, 6] += math.pi  # facing the other way: the same axis, the other front
    a, b = state_targets(box, origin)[0], state_targets(moved, origin)[0]
    torch.testing.assert_close(a[:5], b[:5], atol=1e-5, rtol=0)
    assert a[5] == -b[5]
    back = world_boxes(state_targets(box, origin).numpy(), box[:, :3].numpy(), origin[0].numpy())
    np.testing.assert_allclose(back, box.numpy(), atol=1e-5)


def test_the_tensor_heading_encoding_is_the_scalar_one():
    yaws = torch.linspace(-7, 7, 57, dtype=torch.float64)
    np.testing.assert_allclose(heading_encoding(yaws).numpy(), [heading_targets(float(y)) for y in yaws], atol=1e-12)


def test_the_state_loss_reads_the_road_users_box_through_the_targets_object_channel():
    boxes = torch.tensor([[8.0, 1.0, 0.9, 4.0, 1.9, 1.6, 0.3], [12.0, -3.0, 0.9, 0.6, 0.6, 1.8, -1.2]])
    origins = torch.tensor([[0.0, 0.0, 1.5], [2.0, 2.0, 1.5]])
    targets = torch.zeros(2, 3, 4, 3, TARGET_CHANNELS)
    targets[1, 2, 1, 0, [0, 6, OBJECT]] = torch.tensor([1.0, 1.0, 2.0])  # view 1 holds box row 1
    targets[0, 0, 3, 2, [0, 6, OBJECT]] = torch.tensor([1.0, 1.0, 1.0])  # view 0 holds box row 0
    state = torch.zeros(2, 3, 4, 3, len(STATE), requires_grad=True)
    perfect = state.detach().clone()
    perfect[1, 2, 1, 0] = state_targets(boxes[1:], origins[1:])[0]
    perfect[0, 0, 3, 2] = state_targets(boxes[:1], origins[:1])[0]
    perfect[..., -1] *= 20
    _, right = view_state_loss(perfect, targets, boxes, origins)
    assert right["size"] < 1e-6 and right["heading"] < 1e-6 and right["front"] < 1e-6
    loss, wrong = view_state_loss(state, targets, boxes, origins)
    assert wrong["size"] > 0.1 and wrong["front"] > 0.6
    loss.backward()
    touched = state.grad.abs().sum(-1) > 0
    assert touched.sum() == 2 and touched[1, 2, 1, 0] and touched[0, 0, 3, 2]  # only the anchors holding a road user
    empty, terms = view_state_loss(state, torch.zeros_like(targets), boxes, origins)
    assert float(empty.detach()) == 0 and terms == {}


def test_the_state_changes_none_of_pixelnerf_yolos_yolo_outputs():
    images, K, c2w = smooth_frame()
    outs = {}
    for weight in (0.0, 1.0):
        torch.manual_seed(0)
        cfg = load_config(None, tiny("model.kind=pixelnerf-yolo", f"model.loss.state={weight}"))
        model = build_model(cfg, 2).eval()
        item, _ = frame_item(list(images), list(zip(K, c2w)), cfg.data, ["car", "pedestrian"])
        with torch.no_grad():
            outs[weight] = predict_item(model, item, "cpu", cfg.eval)
    assert outs[0.0].state.shape[-1] == 0 and outs[1.0].state.shape[-1] == len(STATE)
    for field in ("ray_confidence", "box", "class_logits", "depth"):
        assert torch.equal(getattr(outs[0.0], field), getattr(outs[1.0], field)), field


def test_a_checkpoint_from_before_the_state_resolves_to_the_model_it_holds():
    from pnyolo.config import checkpoint_defaults, from_dict, to_dict

    written = to_dict(load_config(None, tiny("model.kind=pixelnerf-yolo")))
    assert written["model"]["loss"]["state"] == 1.0  # today's default: a new run has the state
    before = {**written, "model": {**written["model"], "loss": {k: v for k, v in written["model"]["loss"].items()
                                                               if k != "state"}}}
    assert from_dict(checkpoint_defaults(before)).model.loss.state == 0.0  # trained without it
    assert from_dict(checkpoint_defaults(written)).model.loss.state == 1.0  # a value it names is kept
    assert "state" not in before["model"]["loss"]  # the mapping given is left as it was
    bev = to_dict(load_config(None, tiny("model.kind=bev")))
    assert checkpoint_defaults(bev) == bev
