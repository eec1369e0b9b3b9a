"""Greedy non-maximum suppression (no torchvision)."""
from __future__ import annotations

import torch
from torch import Tensor

from .boxes_torch import box_iou


def nms(boxes: Tensor, scores: Tensor, iou_threshold: float) -> Tensor:
    """Indices of kept boxes (N, 4), highest score first. A box is dropped when its IoU with a
    kept, higher-scoring box exceeds ``iou_threshold`` (torchvision semantics)."""
    if boxes.numel() == 0:
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    order = torch.argsort(scores, descending=True, stable=True)
    iou = box_iou(boxes[order], boxes[order])
    n = order.numel()
    suppressed = torch.zeros(n, dtype=torch.bool, device=boxes.device)
    keep = []
    for i in range(n):
        if suppressed[i]:
            continue
        keep.append(i)
        suppressed |= iou[i] > iou_threshold
    return order[torch.tensor(keep, dtype=torch.long, device=boxes.device)]


def batched_nms(boxes: Tensor, scores: Tensor, classes: Tensor, iou_threshold: float,
                class_agnostic: bool = True) -> Tensor:
    """NMS across all boxes (the original: class-agnostic) or per class."""
    if class_agnostic or boxes.numel() == 0:
        return nms(boxes, scores, iou_threshold)
    offset = (boxes.max() - boxes.min() + 1) * classes.to(boxes.dtype)[:, None]
    return nms(boxes + offset, scores, iou_threshold)
