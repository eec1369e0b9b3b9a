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
from pnyolo.decoding.nms import view_nms
from pnyolo.decoding.world import item_camera, lift_to_world


def decode_outputs(out: RayOutputs, anchors: Tensor, grid: GridSpec, conf_threshold: float,
                   nms_iou: float, depth_gap: float | None = None) -> list[ViewDetections]:
    """Every view's candidates (``RayOutputs.candidates``: the depth peaks, or one per ray and anchor) ->
    detections in encoded-image pixels: thresholded and suppressed for all views at once on the outputs'
    device (greedy NMS within each view, ``nms.view_nms``), copied to the host once."""
    c = out.candidates()
    conf, depth = c.ray_confidence.movedim(-1, 1), c.depth.movedim(-1, 1)  # (V, K, S_h, S_w, A)
    box, logits = c.box.movedim(-2, 1), c.class_logits.movedim(-2, 1)  # (V, K, S_h, S_w, A, 4 | C)
    keep = conf >= conf_threshold
    view = torch.nonzero(keep)[:, 0]
    boxes = yolo_to_box(decode_boxes(box, anchors)[keep], grid.width, grid.height)
    scores, dist = conf[keep], depth[keep]
    classes = logits[keep].argmax(-1) if logits.shape[-1] else torch.zeros_like(scores, dtype=torch.long)
    idx = view_nms(boxes, scores, view, nms_iou, dist, depth_gap)
    kept_view = view[idx]
    host = torch.cat([boxes[idx], scores[idx, None], dist[idx, None], classes[idx, None].to(boxes.dtype),
                      kept_view[:, None].to(boxes.dtype)], dim=1).detach().cpu().double().numpy()  # one copy a frame
    views = host[:, 7].astype(np.int64)
    return [ViewDetections(host[views == v, :4], host[views == v, 4], host[views == v, 6].astype(np.int64),
                           host[views == v, 5]) for v in range(conf.shape[0])]


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
