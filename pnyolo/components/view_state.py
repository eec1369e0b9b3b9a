"""The 3D state a YOLO-grid kind predicts for each anchor beside its box and distance (pixelnerf-yolo): the road
user's size and its heading as the cell's ray sees it, so that a detection at its distance becomes a world box.

    state = [log length, log width, log height, sin 2 alpha, cos 2 alpha, front]      (``STATE``)
    alpha = yaw - azimuth of the line from the camera to the box centre           (about world z)

The heading relative to that line (KITTI's observation angle) is what an image shows: a car seen from behind looks
the same wherever it stands, while its world yaw depends on where the camera points, which the samples' inputs (points
and directions in each camera's axes) do not carry in one frame. It is encoded as an axis and a front sign
(``pnyolo.components.heading``), as the bev head's heading is. The targets come from the item's 3D boxes through the
YOLO targets' ``object`` channel::

    loss, terms = view_state_loss(out.state, targets, item.boxes_3d, origins)     # origins (V, 3) camera centres
    boxes = world_boxes(state, centres, origin)        # (P, 7) [cx, cy, cz, length, width, height, yaw]
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from pnyolo.components.heading import decode_heading, heading_encoding
from pnyolo.data.targets import OBJ, OBJECT

STATE = ("log_length", "log_width", "log_height", "sin_2alpha", "cos_2alpha", "front")
SIZE, AXIS, FRONT = slice(0, 3), slice(3, 5), 5
WEIGHT = 6  # the YOLO targets' loss-weight channel
MAX_LOG_SIZE = 4.0  # clamp on a decoded log size (metres), as the bev head's


def ray_azimuth(centres: Tensor, origins: Tensor) -> Tensor:
    """(...,) the world azimuth (radians, about z) of the line from each camera centre ``origins`` (..., 3) to each
    point ``centres`` (..., 3)."""
    d = centres[..., :2] - origins[..., :2]
    return torch.atan2(d[..., 1], d[..., 0])


def state_targets(boxes: Tensor, origins: Tensor) -> Tensor:
    """World boxes (P, 7) [cx, cy, cz, length, width, height, yaw] seen from cameras at ``origins`` (P, 3) -> their
    states (P, 6) (``STATE``)."""
    alpha = boxes[:, 6] - ray_azimuth(boxes[:, :3], origins)
    return torch.cat([boxes[:, 3:6].clamp_min(1e-3).log(), heading_encoding(alpha)], dim=-1)


def state_loss(pred: Tensor, target: Tensor, weight: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
    """Predicted states (P, 6) against targets (P, 6), each road user weighted by ``weight`` (P,): L1 on the log
    sizes and on the axis, binary cross-entropy on the front (a logit against +1 / -1), each a weighted mean."""
    total = weight.sum().clamp_min(1e-12)
    mean = lambda per: (per * weight).sum() / total  # noqa: E731
    diff = (pred - target).abs()
    terms = {"size": mean(diff[:, SIZE].mean(-1)), "heading": mean(diff[:, AXIS].mean(-1)),
             "front": mean(F.binary_cross_entropy_with_logits(pred[:, FRONT], (target[:, FRONT] > 0).to(pred.dtype),
                                                              reduction="none"))}
    return sum(terms.values()), terms


def view_state_loss(state: Tensor, targets: Tensor, boxes_3d: Tensor | None,
                    origins: Tensor) -> tuple[Tensor, dict[str, float]]:
    """``state_loss`` of a grid's states (V, S_h, S_w, A, 6) at the anchors whose YOLO targets (V, S_h, S_w, A, 9)
    hold a road user with a 3D box (``object`` channel), seen from view v's camera centre ``origins[v]`` (V, 3)."""
    held = (targets[..., 0] == OBJ) & (targets[..., OBJECT] > 0)
    if boxes_3d is None or not bool(held.any()):
        return state.sum() * 0.0, {}
    t = targets[held]
    views = held.nonzero()[:, 0]
    boxes = boxes_3d.to(state)[t[:, OBJECT].long() - 1]
    loss, terms = state_loss(state[held], state_targets(boxes, origins.to(state)[views]), t[:, WEIGHT])
    return loss, {k: float(v.detach()) for k, v in terms.items()}


def world_boxes(state: np.ndarray, centres: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Detections' states (P, 6) at world ``centres`` (P, 3), seen from the camera centre ``origin`` (3,) -> world
    boxes (P, 7) [cx, cy, cz, length, width, height, yaw] (yaw in (-pi, pi])."""
    s = torch.as_tensor(np.asarray(state, dtype=np.float64)).reshape(-1, len(STATE))
    c = torch.as_tensor(np.asarray(centres, dtype=np.float64)).reshape(-1, 3)
    yaw = decode_heading(s[:, AXIS][:, 0], s[:, AXIS][:, 1], s[:, FRONT])
    yaw = yaw + ray_azimuth(c, torch.as_tensor(np.asarray(origin, dtype=np.float64))[None])
    yaw = torch.atan2(torch.sin(yaw), torch.cos(yaw))
    return torch.cat([c, s[:, SIZE].clamp(max=MAX_LOG_SIZE).exp(), yaw[:, None]], dim=1).numpy()
