"""A YOLO grid's outputs (pixelnerf-yolo, single-view) to detections per view: decode, confidence
threshold, NMS (``eval.depth_gap``: boxes whose distance estimates differ by more than that many
metres do not suppress each other); detections with a distance also get a world centre (the ray
through the box centre at that distance)::

    dets = decode_with(out, model.anchors, item.grid, cfg.eval)    # ViewDetections per view
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from pnyolo.components.boxes import yolo_to_box
from pnyolo.components.renderer import RayOutputs
from pnyolo.config import EvalConfig
from pnyolo.data.grid import GridSpec
from pnyolo.data.item import Item
from pnyolo.data.targets import decode_boxes
from pnyolo.decoding.detections import ViewDetections
from pnyolo.decoding.nms import batched_nms
from pnyolo.decoding.world import item_camera, lift_to_world


def decode_view(conf: Tensor, box: Tensor, class_logits: Tensor, depth: Tensor, anchors: Tensor, grid: GridSpec,
                conf_threshold: float, nms_iou: float, class_agnostic: bool = True,
                depth_gap: float | None = None) -> ViewDetections:
    """One view's candidates (S_h, S_w, A, K, ...) (K: depth peaks per ray and anchor, 1 without)
    -> detections in encoded-image pixels."""
    conf, depth = conf.movedim(-1, 0), depth.movedim(-1, 0)  # (K, S_h, S_w, A)
    box, class_logits = box.movedim(-2, 0), class_logits.movedim(-2, 0)
    yolo = decode_boxes(box, anchors)  # (K, S_h, S_w, A, 4)
    keep = conf >= conf_threshold
    boxes = yolo_to_box(yolo[keep], grid.width, grid.height)
    scores = conf[keep]
    classes = class_logits[keep].argmax(-1) if class_logits.shape[-1] else torch.zeros_like(scores, dtype=torch.long)
    dist = depth[keep]
    idx = batched_nms(boxes, scores, classes, nms_iou, class_agnostic, dist, depth_gap)
    return ViewDetections(boxes[idx].detach().cpu().double().numpy(), scores[idx].detach().cpu().double().numpy(),
                          classes[idx].cpu().numpy().astype(np.int64), dist[idx].detach().cpu().double().numpy())


def decode_outputs(out: RayOutputs, anchors: Tensor, grid: GridSpec, conf_threshold: float,
                   nms_iou: float, depth_gap: float | None = None) -> list[ViewDetections]:
    """Every view's candidates (``RayOutputs.candidates``: the depth peaks, or one per ray and anchor)."""
    c = out.candidates()
    return [decode_view(c.ray_confidence[v], c.box[v], c.class_logits[v], c.depth[v], anchors, grid,
                        conf_threshold, nms_iou, depth_gap=depth_gap) for v in range(c.ray_confidence.shape[0])]


def decode_with(out: RayOutputs, anchors: Tensor, grid: GridSpec, ev: EvalConfig,
                conf_threshold: float | None = None) -> list[ViewDetections]:
    """``decode_outputs`` with an evaluation config's threshold and NMS settings (``conf_threshold``
    overrides its threshold)."""
    return decode_outputs(out, anchors, grid, ev.conf_threshold if conf_threshold is None else conf_threshold,
                          ev.nms_iou, ev.depth_gap)


def with_centres(det: ViewDetections, item: Item, v: int) -> ViewDetections:
    """``det`` of view ``v`` with world centres lifted from its distances (unchanged without them)."""
    if det.distances is None or not np.isfinite(det.distances).all():
        return det
    return replace(det, centres=lift_to_world(det, *item_camera(item, v)))
