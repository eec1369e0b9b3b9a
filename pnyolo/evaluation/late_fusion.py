"""Late fusion: each car detects on its own camera alone and sends its 3D detections; the detections
of every car are pooled in the world frame (one per road user: same-class centres closer than
``eval.centre_nms_m`` merged, the higher score kept) and projected into each target view.

    dets, sent = late_fusion(bev_model, item, "cpu", cfg.eval)   # ViewDetections per view, bytes sent

A car sends ``WorldDetections.nbytes()`` per frame: 36 bytes a detection, against the encoder
feature maps that the multi-view models read from its camera (``feature_bytes``).
"""
from __future__ import annotations

import torch

from dataset_spec.cli_support import UserError
from pnyolo.config import EvalConfig
from pnyolo.evaluation.metrics import ViewDetections
from pnyolo.evaluation.world import WorldDetections, centre_nms, project_into_views
from pnyolo.models import predict_item


def check_late_fusion(model) -> None:
    """One-line error for a model without 3D detections."""
    if not getattr(model, "world_grid", False):
        raise UserError(f"--late-fusion needs a model with 3D detections (model.kind bev), not {model.cfg.model.kind}")


@torch.no_grad()
def late_fusion(model, item: dict, device, ev: EvalConfig, threshold: float | None = None, own_view_out=None,
                pose_noise=None) -> tuple[list[ViewDetections], int]:
    """Every view's detections after pooling each source view's own (``model`` run on each alone),
    and the bytes all cars sent (``threshold`` overrides ``ev.conf_threshold``; ``own_view_out``: the
    model's ``own_view_only`` outputs for ``item`` if already computed; ``pose_noise``: a
    ``PoseNoise`` by which each target view's car places the others' detections)."""
    check_late_fusion(model)
    t = ev.conf_threshold if threshold is None else threshold
    out = own_view_out if own_view_out is not None else predict_item(model, item, device, own_view_only=True)
    top_k = model.cfg.model.bev.top_k
    cars = [out.world_detections(b, t, top_k, ev.centre_nms_m) for b in range(out.view_sets.shape[0])]
    sent = sum(c.nbytes() for c in cars)
    if pose_noise is None or not pose_noise.active:
        return fuse_cars(cars, item, ev.centre_nms_m), sent
    fused = fuse_cars(cars, item, ev.centre_nms_m)  # the views not scored keep these
    for v in item["scored"]:
        placed = [WorldDetections(pose_noise.boxes_from(item, b, c.boxes, v), c.scores, c.classes)
                  for b, c in enumerate(cars)]
        fused[v] = fuse_cars(placed, item, ev.centre_nms_m)[v]
    return fused, sent


def fuse_cars(cars: list[WorldDetections], item: dict, radius: float) -> list[ViewDetections]:
    """Several cars' 3D detections pooled (one per road user within ``radius`` metres) and
    projected into the item's scored views."""
    return project_into_views(centre_nms(WorldDetections.concat(cars), radius), item, item["scored"])


def feature_bytes(model, item: dict, device) -> int:
    """Bytes of one view's encoder feature maps (float32): what a multi-view model reads from another car."""
    with torch.no_grad():
        feats = model.encoder(item["images"][:1].to(device))
    return sum(f[0].numel() * 4 for f in feats)
