"""Greedy non-maximum suppression (no torchvision), optionally gated by distance.

With ``depth_gap`` a box suppresses another only when their distance estimates (metres along the
ray, ``RayOutputs.depth``) differ by at most ``depth_gap``: a road user hidden behind another one
has nearly the same image box as its occluder but a larger distance, so it survives. Boxes without
a distance (NaN, e.g. the single-view model's) suppress and are suppressed as in plain NMS.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from pnyolo.components.boxes import box_iou


def nms(boxes: Tensor, scores: Tensor, iou_threshold: float, depths: Tensor | None = None,
        depth_gap: float | None = None, groups: Tensor | None = None) -> Tensor:
    """Indices of kept boxes (N, 4), highest score first. A box is dropped when its IoU with a
    kept, higher-scoring box exceeds ``iou_threshold`` (torchvision semantics) and, with
    ``depth_gap`` and ``depths`` (N,), their distances differ by at most ``depth_gap`` (or either is NaN);
    with ``groups`` (N,) only boxes of one group suppress each other. Computed on the boxes' device."""
    if boxes.numel() == 0:
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    order = torch.argsort(scores, descending=True, stable=True)
    if groups is not None and boxes.device.type == "cpu":  # one group at a time: matrices and loops V times smaller
        g = groups[order]
        parts = [torch.nonzero(g == value).squeeze(1) for value in torch.unique(g)]
        kept = [p[greedy_keep(_overlaps(boxes, order[p], iou_threshold, depths, depth_gap))] for p in parts]
        return order[torch.sort(torch.cat(kept)).values]  # every group's kept boxes, highest score first
    overlapping = _overlaps(boxes, order, iou_threshold, depths, depth_gap)
    if groups is not None:  # all groups at once (a GPU): the pairs of two groups never overlap
        g = groups[order]
        overlapping &= g[:, None] == g[None, :]
    return order[greedy_keep(overlapping)]


def _overlaps(boxes: Tensor, order: Tensor, iou_threshold: float, depths: Tensor | None, depth_gap: float | None
              ) -> Tensor:
    """(n, n) bool over ``boxes[order]``: box i would suppress the later box j (IoU above the threshold, distances
    within ``depth_gap`` where given), upper triangle only."""
    overlapping = box_iou(boxes[order], boxes[order]) > iou_threshold
    if depth_gap is not None and depths is not None:
        d = depths[order].to(torch.float64)
        apart = (d[:, None] - d[None, :]).abs() > depth_gap  # False where either is NaN
        overlapping &= ~apart
    return overlapping.triu(1)


def greedy_keep(overlapping: Tensor, rounds: bool | None = None) -> Tensor:
    """Greedy suppression in order (row i suppresses the later boxes it overlaps, if i is kept) as a boolean mask.
    On the CPU box by box; on a GPU without a host round trip per box: keep[i] = no kept j < i overlaps i, solved
    by iterating that rule on all boxes at once (box i is settled after at most i rounds; the rounds stop when
    nothing changes, usually after a few). Both give the same boxes; ``rounds`` None: rounds off the CPU."""
    n = overlapping.shape[0]
    if not (overlapping.device.type != "cpu" if rounds is None else rounds):
        rows = overlapping.numpy()
        suppressed = np.zeros(n, dtype=bool)
        i = 0
        while i < n:  # from one kept box to the next: a loop over the kept boxes only
            suppressed |= rows[i]
            later = np.flatnonzero(~suppressed[i + 1:])
            i = i + 1 + int(later[0]) if len(later) else n
        return torch.from_numpy(~suppressed)
    keep = torch.ones(n, dtype=torch.bool, device=overlapping.device)
    for _ in range(n):
        new = ~(overlapping & keep[:, None]).any(dim=0)
        if torch.equal(new, keep):
            break
        keep = new
    return keep


def view_nms(boxes: Tensor, scores: Tensor, views: Tensor, iou_threshold: float, depths: Tensor | None = None,
             depth_gap: float | None = None) -> Tensor:
    """Class-agnostic greedy NMS within each view (``views`` (N,)), all views in one pass (``nms``)."""
    return nms(boxes, scores, iou_threshold, depths, depth_gap, groups=views)


def batched_nms(boxes: Tensor, scores: Tensor, classes: Tensor, iou_threshold: float,
                class_agnostic: bool = True, depths: Tensor | None = None, depth_gap: float | None = None) -> Tensor:
    """NMS across all boxes (the original: class-agnostic) or per class; ``depths``/``depth_gap`` as in ``nms``."""
    if class_agnostic or boxes.numel() == 0:
        return nms(boxes, scores, iou_threshold, depths, depth_gap)
    offset = (boxes.max() - boxes.min() + 1) * classes.to(boxes.dtype)[:, None]
    return nms(boxes + offset, scores, iou_threshold, depths, depth_gap)
