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

from pnyolo.decoding.detections import ViewDetections, union
from pnyolo.decoding.nms import batched_nms


def fuse_detections(a: ViewDetections, b: ViewDetections, nms_iou: float, class_agnostic: bool = True,
                    depth_gap: float | None = None) -> ViewDetections:
    """Union of ``a`` and ``b`` followed by NMS at ``nms_iou`` (class-agnostic like the original),
    gated by distance with ``depth_gap`` (see ``nms.nms``; detections without a distance are not gated)."""
    both = union(a, b)
    keep = batched_nms(torch.from_numpy(both.boxes), torch.from_numpy(both.scores), torch.from_numpy(both.classes),
                       nms_iou, class_agnostic, torch.from_numpy(both.distances), depth_gap).numpy()
    return both.take(np.sort(keep) if len(keep) else keep)  # keep input order: a's detections first
