"""Detections in the world frame: 3D boxes, merging them, and putting them into camera views.

    dets = heatmap_detections(heatmap, regression, grid, 0.3)   # CenterNet heads on a ground grid -> WorldDetections
    dets = centre_nms(WorldDetections.concat([car_a, car_b]), 1.0)   # late fusion: one per road user
    views = project_into_views(dets, item, item.scored)     # ViewDetections per view, as labels are
    centres = lift_to_world(view_dets, K, camera_to_world)     # a 2D model's detections at their distance

``project_into_views`` treats a 3D detection exactly as the projection tool treats a labelled
road user (``tools.projection``; both by ``dataset_spec.boxes.box_in_view``): near-plane clipped,
projected, clipped to the image, then the view's label thresholds (in-frame fraction of the 3D box,
distance, box size in the renders' pixels; a detection has no visibility, so a minimum visible
fraction is not applied), and the car carrying the camera (its box holds the camera) is left out.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from dataset_spec.camera import pixel_rays
from pnyolo.components.bev_grid import BevGrid
from pnyolo.components.bev_targets import REGRESSION, decode_regression
from pnyolo.data.item import Item
from pnyolo.decoding.box_views import boxes_in_views, in_frame
from pnyolo.decoding.detections import ViewDetections, WorldDetections


def heatmap_detections(heatmap: Tensor, regression: Tensor, grid: BevGrid, threshold: float, top_k: int = 100,
                       nms_m: float = 0.0) -> WorldDetections:
    """A ground grid's CenterNet outputs -> world boxes: the peaks (3x3 local maxima) of the class heatmaps
    (C, ny, nx; logits) scoring at least ``threshold``, at most ``top_k``, each box from the regression
    (9, ny, nx; ``components.bev_targets.REGRESSION``) at its cell; same-class centres within ``nms_m``
    merged (0: none)."""
    heat = torch.sigmoid(heatmap.detach().float())
    C, ny, nx = heat.shape
    peaks = heat * (heat == F.max_pool2d(heat[None], 3, 1, 1)[0])
    # by score, equal scores by flat index (class, row, column): what a caller of the exported graph reproduces
    flat = torch.argsort(-peaks.reshape(-1), stable=True)[: min(top_k, peaks.numel())]
    scores = peaks.reshape(-1)[flat]
    keep = scores >= threshold
    scores, flat = scores[keep], flat[keep]
    cells = flat % (ny * nx)
    values = regression.detach().float().reshape(len(REGRESSION), -1)[:, cells].T
    boxes = decode_regression(values, cells, grid)
    dets = WorldDetections(boxes.cpu().double().numpy(), scores.cpu().double().numpy(),
                           (flat // (ny * nx)).cpu().numpy().astype("int64"))
    return centre_nms(dets, nms_m) if nms_m > 0 else dets


def centre_nms(dets: WorldDetections, radius: float) -> WorldDetections:
    """Greedy by score: a detection is dropped when a kept one of its class has its ground-plane
    centre closer than ``radius`` metres."""
    order = np.argsort(-dets.scores, kind="stable")
    kept: list[int] = []
    for i in order:
        xy, c = dets.boxes[i, :2], dets.classes[i]
        if all(dets.classes[k] != c or np.hypot(*(dets.boxes[k, :2] - xy)) >= radius for k in kept):
            kept.append(int(i))
    return dets.take(np.asarray(kept, dtype=np.int64))


def pool_views(parts: list[WorldDetections], radius: float) -> WorldDetections:
    """One set of 3D detections from ``parts`` that may report a road user more than once (each view's of one item,
    each item's of one sample, each car's): same-class centres within ``radius`` metres merged (``centre_nms``; a part
    its kind merged already, score-ordered, comes back as it was)."""
    return centre_nms(WorldDetections.concat(parts), radius) if parts else WorldDetections.empty()


def item_camera(item: Item, v: int) -> tuple[np.ndarray, np.ndarray]:
    """View ``v``'s (K, camera_to_world) of an item, float64 numpy (at the item's image size)."""
    return item.K[v].cpu().numpy().astype(np.float64), item.camera_to_world[v].cpu().numpy().astype(np.float64)


def project_into_views(dets: WorldDetections, item: Item, views: list[int]) -> list[ViewDetections]:
    """``dets`` as each of the item's views would label them (the module docstring); views not in
    ``views`` get no detections. Each detection keeps its world centre and its distance. Every detection and
    view at once on the item's device (``box_views.boxes_in_views``), one copy to the host."""
    g, V = item.grid, len(item.K)
    if not len(dets) or not views:
        return [_view_detections(dets, np.zeros(0, np.int64), np.zeros((0, 4)), np.zeros(0)) for _ in range(V)]
    K, c2w = item.K.double(), item.camera_to_world.double()
    boxes = torch.as_tensor(dets.boxes, dtype=torch.float64, device=K.device)
    cams = item.cameras
    seen = boxes_in_views(boxes, K, c2w, g.width, g.height, K.new_tensor([c.near for c in cams]),
                          K.new_tensor([c.far for c in cams]))
    limits = _limits(item, dets.classes)  # (V, P, 3): max distance, min box pixels, min in-frame
    scale = K.new_tensor([[g.width / c.size[0], g.height / c.size[1]] for c in cams])  # (V, 2)
    px = (seen.box[..., 2:] - seen.box[..., :2]) / scale[:, None, :]
    keep = seen.valid & ~seen.holds_camera & (seen.distance <= limits[..., 0]) & (px.amin(dim=-1) >= limits[..., 1])
    keep[[v for v in range(V) if v not in views]] = False
    near = K.new_tensor([c.near for c in cams])
    keep &= in_frame(boxes, K, c2w, g.width, g.height, near, keep) >= limits[..., 2]  # the costly rule last
    host = torch.cat([keep[..., None].double(), seen.box, seen.distance[..., None]], dim=-1).cpu().numpy()
    return [_view_detections(dets, np.nonzero(host[v, :, 0] > 0)[0], host[v, :, 1:5], host[v, :, 5]) for v in range(V)]


def _limits(item: Item, classes: np.ndarray) -> Tensor:
    """(V, P, 3) each detection's thresholds in each view (its class's: max distance (inf: none), min box
    pixels, min in-frame share)."""
    rows = []
    for cam in item.cameras:
        per_class = [cam.thresholds.for_class(name) for name in item.class_names]
        table = [[np.inf if t.max_distance is None else t.max_distance, t.min_box_pixels, t.min_in_frame]
                 for t in per_class]
        rows.append(np.asarray(table, dtype=np.float64)[np.asarray(classes, dtype=np.int64)].reshape(-1, 3))
    return torch.as_tensor(np.stack(rows), device=item.K.device)


def _view_detections(dets: WorldDetections, k: np.ndarray, boxes: np.ndarray, distances: np.ndarray) -> ViewDetections:
    """The detections ``k`` of ``dets`` with their boxes and distances in one view."""
    return ViewDetections(boxes[k].reshape(-1, 4), dets.scores[k].astype(np.float64), dets.classes[k].astype(np.int64),
                          distances[k].astype(np.float64), centres=dets.boxes[k, :3].astype(np.float64),
                          world_boxes=dets.boxes[k].astype(np.float64).reshape(-1, 7),
                          velocities=None if dets.velocities is None else dets.velocities[k],
                          attributes=None if dets.attributes is None else [dets.attributes[i] for i in k])


def lift_to_world(det: ViewDetections, K: np.ndarray, camera_to_world: np.ndarray) -> np.ndarray:
    """(P, 3) world centres of 2D detections: the ray through each box's centre pixel, at the
    detection's distance along it (NaN without a distance)."""
    if det.distances is None or len(det.boxes) == 0:
        return np.full((len(det.boxes), 3), np.nan)
    centre_px = np.stack([(det.boxes[:, 0] + det.boxes[:, 2]) / 2, (det.boxes[:, 1] + det.boxes[:, 3]) / 2], axis=-1)
    origins, dirs = pixel_rays(K, camera_to_world, centre_px)
    return origins + dirs * np.asarray(det.distances, dtype=np.float64)[:, None]
