"""2D box helpers in torch. Boxes are ``[x0, y0, x1, y1]``; YOLO boxes ``[cx, cy, w, h]`` fractions.

Same conventions as ``dataset_spec.boxes`` (pixel (u, v) centred at (u, v); the image spans
[-0.5, W-0.5]), so ``yolo_to_box(box_to_yolo(b))`` is the identity.
"""
from __future__ import annotations

import torch
from torch import Tensor


def box_area(boxes: Tensor) -> Tensor:
    return (boxes[..., 2] - boxes[..., 0]).clamp_min(0) * (boxes[..., 3] - boxes[..., 1]).clamp_min(0)


def box_iou(a: Tensor, b: Tensor) -> Tensor:
    """Pairwise IoU (N, 4) x (M, 4) -> (N, M); 0 where the union is empty."""
    lt = torch.maximum(a[:, None, :2], b[None, :, :2])
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = (rb - lt).clamp_min(0).prod(dim=-1)
    union = box_area(a)[:, None] + box_area(b)[None, :] - inter
    return torch.where(union > 0, inter / union.clamp_min(1e-12), torch.zeros_like(union))


def _overlap_cxcywh(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Intersection, union and smallest enclosing box area of matching (cx, cy, w, h) boxes."""
    a0, a1 = a[..., :2] - a[..., 2:] / 2, a[..., :2] + a[..., 2:] / 2
    b0, b1 = b[..., :2] - b[..., 2:] / 2, b[..., :2] + b[..., 2:] / 2
    inter = (torch.minimum(a1, b1) - torch.maximum(a0, b0)).clamp_min(0).prod(dim=-1)
    union = a[..., 2:].clamp_min(0).prod(-1) + b[..., 2:].clamp_min(0).prod(-1) - inter
    hull = (torch.maximum(a1, b1) - torch.minimum(a0, b0)).clamp_min(0).prod(dim=-1)
    return inter, union, hull


def elementwise_iou_cxcywh(a: Tensor, b: Tensor) -> Tensor:
    """IoU of matching boxes (..., 4) and (..., 4) in (cx, cy, w, h)."""
    inter, union, _ = _overlap_cxcywh(a, b)
    return inter / union.clamp_min(1e-12)


def generalized_iou_cxcywh(a: Tensor, b: Tensor) -> Tensor:
    """Generalised IoU (Rezatofighi et al. 2019) of matching boxes (..., 4) and (..., 4) in
    (cx, cy, w, h): IoU minus the share of the smallest enclosing box that neither box covers.
    In [-1, 1]; unlike IoU it still has a gradient when the boxes do not overlap."""
    inter, union, hull = _overlap_cxcywh(a, b)
    return inter / union.clamp_min(1e-12) - (hull - union) / hull.clamp_min(1e-12)


def yolo_to_box(yolo: Tensor, width: float, height: float) -> Tensor:
    """(..., 4) [cx, cy, w, h] fractions -> [x0, y0, x1, y1] pixels."""
    cx, cy = yolo[..., 0] * width - 0.5, yolo[..., 1] * height - 0.5
    hw, hh = yolo[..., 2] * width / 2, yolo[..., 3] * height / 2
    return torch.stack([cx - hw, cy - hh, cx + hw, cy + hh], dim=-1)


def box_to_yolo(box: Tensor, width: float, height: float) -> Tensor:
    """(..., 4) [x0, y0, x1, y1] pixels -> [cx, cy, w, h] fractions."""
    return torch.stack([((box[..., 0] + box[..., 2]) / 2 + 0.5) / width, ((box[..., 1] + box[..., 3]) / 2 + 0.5) / height,
                        (box[..., 2] - box[..., 0]) / width, (box[..., 3] - box[..., 1]) / height], dim=-1)
