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

from pnyolo.evaluation.metrics import ViewDetections
from pnyolo.decoding.nms import batched_nms


def fuse_detections(a: ViewDetections, b: ViewDetections, nms_iou: float, class_agnostic: bool = True,
                    depth_gap: float | None = None) -> ViewDetections:
    """Union of ``a`` and ``b`` followed by NMS at ``nms_iou`` (class-agnostic like the original),
    gated by distance with ``depth_gap`` (see ``nms.nms``; detections without a distance are not gated)."""

    def dist(d: ViewDetections) -> np.ndarray:
        return np.full(len(d.boxes), np.nan) if d.distances is None else np.asarray(d.distances, dtype=np.float64)

    boxes = np.concatenate([np.asarray(a.boxes, dtype=np.float64).reshape(-1, 4),
                            np.asarray(b.boxes, dtype=np.float64).reshape(-1, 4)])
    scores = np.concatenate([np.asarray(a.scores, dtype=np.float64), np.asarray(b.scores, dtype=np.float64)])
    classes = np.concatenate([np.asarray(a.classes, dtype=np.int64), np.asarray(b.classes, dtype=np.int64)])
    def centres(d: ViewDetections) -> np.ndarray:
        return np.full((len(d.boxes), 3), np.nan) if d.centres is None else np.asarray(d.centres, dtype=np.float64)

    distances = np.concatenate([dist(a), dist(b)])
    keep = batched_nms(torch.from_numpy(boxes), torch.from_numpy(scores), torch.from_numpy(classes), nms_iou,
                       class_agnostic, torch.from_numpy(distances), depth_gap).numpy()
    keep = np.sort(keep) if len(keep) else keep  # keep input order: a's detections first
    both = None if a.centres is None and b.centres is None else np.concatenate([centres(a), centres(b)])[keep]
    return ViewDetections(boxes[keep], scores[keep], classes[keep], distances[keep], both)
