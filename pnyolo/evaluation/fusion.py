"""Prediction fusion (the paper's Table 6.11): union of two detectors' detections, then NMS.

Example::

    fused = fuse_detections(multi_view_dets, single_view_dets, nms_iou=0.5)

Both inputs must be in the same pixel frame (same encoded image size). Where both detectors
find an object, NMS keeps the higher-scoring box; a detection only one of them makes survives.
Fusing a set with itself returns the set unchanged.
"""
from __future__ import annotations

import numpy as np
import torch

from dataset_spec.boxes import box_iou
from pnyolo.evaluation.metrics import ViewDetections
from pnyolo.decoding.nms import batched_nms


def union(a: ViewDetections, b: ViewDetections) -> ViewDetections:
    """``a``'s detections then ``b``'s (distances and centres NaN where one side has none)."""

    def dist(d: ViewDetections) -> np.ndarray:
        return np.full(len(d.boxes), np.nan) if d.distances is None else np.asarray(d.distances, dtype=np.float64)

    def centres(d: ViewDetections) -> np.ndarray:
        return np.full((len(d.boxes), 3), np.nan) if d.centres is None else np.asarray(d.centres, dtype=np.float64)

    return ViewDetections(np.concatenate([np.asarray(a.boxes, dtype=np.float64).reshape(-1, 4),
                                          np.asarray(b.boxes, dtype=np.float64).reshape(-1, 4)]),
                          np.concatenate([np.asarray(a.scores, dtype=np.float64), np.asarray(b.scores, dtype=np.float64)]),
                          np.concatenate([np.asarray(a.classes, dtype=np.int64), np.asarray(b.classes, dtype=np.int64)]),
                          np.concatenate([dist(a), dist(b)]),
                          None if a.centres is None and b.centres is None else np.concatenate([centres(a), centres(b)]))


def fuse_detections(a: ViewDetections, b: ViewDetections, nms_iou: float, class_agnostic: bool = True,
                    depth_gap: float | None = None) -> ViewDetections:
    """Union of ``a`` and ``b`` followed by NMS at ``nms_iou`` (class-agnostic like the original),
    gated by distance with ``depth_gap`` (see ``nms.nms``; detections without a distance are not gated)."""
    both = union(a, b)
    keep = batched_nms(torch.from_numpy(both.boxes), torch.from_numpy(both.scores), torch.from_numpy(both.classes),
                       nms_iou, class_agnostic, torch.from_numpy(both.distances), depth_gap).numpy()
    return both.take(np.sort(keep) if len(keep) else keep)  # keep input order: a's detections first


def add_reports(own: ViewDetections, reports: ViewDetections, nms_iou: float) -> ViewDetections:
    """``own`` with each of ``reports`` (other road users, already one each) whose box overlaps none of
    ``own``'s by more than ``nms_iou``: neither side's boxes suppress their own side's, so a reported road
    user hidden behind another report survives (class-agnostic)."""
    if len(own.boxes) and len(reports.boxes):
        reports = reports.take(box_iou(reports.boxes, own.boxes).max(axis=1) <= nms_iou)
    return union(own, reports)
