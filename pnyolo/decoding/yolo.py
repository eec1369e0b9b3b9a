"""A YOLO grid's outputs (pixelnerf-yolo, single-view) to detections per view: decode, confidence
threshold, NMS (``eval.depth_gap``: boxes whose distance estimates differ by more than that many
metres do not suppress each other); given the views' cameras, detections with a distance also get a
world centre (the ray through the box centre at that distance) and, with a 3D state in the outputs
(``pnyolo.components.view_state``), a world box there::

    dets = decode_with(out, model.anchors, item.grid, cfg.eval, cameras=item_cameras(item))   # ViewDetections
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from pnyolo.components.boxes import yolo_to_box
from pnyolo.components.renderer import RayOutputs
from pnyolo.components.view_state import world_boxes
from pnyolo.config import EvalConfig
from pnyolo.data.grid import GridSpec
from pnyolo.data.item import Item
from pnyolo.data.targets import decode_boxes
from pnyolo.decoding.detections import ViewDetections
from pnyolo.decoding.nms import view_nms
from pnyolo.decoding.world import item_camera, lift_to_world


def decode_outputs(out: RayOutputs, anchors: Tensor, grid: GridSpec, conf_threshold: float, nms_iou: float,
                   depth_gap: float | None = None, cameras: list[tuple[np.ndarray, np.ndarray]] | None = None
                   ) -> list[ViewDetections]:
    """Every view's candidates (``RayOutputs.candidates``: the depth peaks, or one per ray and anchor) ->
    detections in encoded-image pixels: thresholded and suppressed for all views at once on the outputs'
    device (greedy NMS within each view, ``nms.view_nms``), copied to the host once; with each view's
    ``cameras`` (K, camera_to_world) placed in the world (``placed``)."""
    c = out.candidates()
    conf, depth = c.ray_confidence.movedim(-1, 1), c.depth.movedim(-1, 1)  # (V, K, S_h, S_w, A)
    box, logits = c.box.movedim(-2, 1), c.class_logits.movedim(-2, 1)  # (V, K, S_h, S_w, A, 4 | C)
    state = c.state.movedim(-2, 1)  # (V, K, S_h, S_w, A, D)
    keep = conf >= conf_threshold
    view = torch.nonzero(keep)[:, 0]
    boxes = yolo_to_box(decode_boxes(box, anchors)[keep], grid.width, grid.height)
    scores, dist = conf[keep], depth[keep]
    classes = logits[keep].argmax(-1) if logits.shape[-1] else torch.zeros_like(scores, dtype=torch.long)
    idx = view_nms(boxes, scores, view, nms_iou, dist, depth_gap)
    kept_view = view[idx]
    host = torch.cat([boxes[idx], scores[idx, None], dist[idx, None], classes[idx, None].to(boxes.dtype),
                      kept_view[:, None].to(boxes.dtype), state[keep][idx].to(boxes.dtype)],
                     dim=1).detach().cpu().double().numpy()  # one copy a frame
    views = host[:, 7].astype(np.int64)
    dets = [ViewDetections(host[views == v, :4], host[views == v, 4], host[views == v, 6].astype(np.int64),
                           host[views == v, 5]) for v in range(conf.shape[0])]
    if cameras is None:
        return dets
    return [placed(d, host[views == v, 8:], *cameras[v]) for v, d in enumerate(dets)]


def decode_with(out: RayOutputs, anchors: Tensor, grid: GridSpec, ev: EvalConfig, conf_threshold: float | None = None,
                cameras: list[tuple[np.ndarray, np.ndarray]] | None = None) -> list[ViewDetections]:
    """``decode_outputs`` with an evaluation config's threshold and NMS settings (``conf_threshold``
    overrides its threshold)."""
    return decode_outputs(out, anchors, grid, ev.conf_threshold if conf_threshold is None else conf_threshold,
                          ev.nms_iou, ev.depth_gap, cameras)


def item_cameras(item: Item) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every view's (K, camera_to_world) of an item (``world.item_camera``)."""
    return [item_camera(item, v) for v in range(len(item.K))]


def placed(det: ViewDetections, state: np.ndarray, K: np.ndarray, camera_to_world: np.ndarray) -> ViewDetections:
    """One view's detections with world centres lifted from their distances, and world boxes from their states
    (P, D) where D > 0 (``view_state.world_boxes``); unchanged where a distance is missing."""
    if det.distances is None or not np.isfinite(det.distances).all():
        return det
    centres = lift_to_world(det, K, camera_to_world)
    boxes = world_boxes(state, centres, camera_to_world[:3, 3]) if state.shape[1] else None
    return replace(det, centres=centres, world_boxes=boxes)
