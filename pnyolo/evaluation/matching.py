"""How detections (``pnyolo.decoding.detections``) are matched to a view's ground truth
(``pnyolo.data.item.ViewGroundTruth``): the primitives every metric (``metrics``, ``metrics_3d``,
``metrics_bins``) builds on.

    pairs = strict_pairs(det, gt, 0.5)          # (P,) the ground truth each detection matched, -1: none
    skip = ignored_predictions(det, gt, pairs >= 0, 0.5)   # on excluded road users: neither TP nor FP
    ap = precision_recall_ap(scores, is_tp, n_gt)
"""
from __future__ import annotations

import numpy as np

from dataset_spec.boxes import box_area, box_iou
from pnyolo.data.item import ViewGroundTruth
from pnyolo.decoding.detections import ViewDetections


def strict_pairs(det: ViewDetections, gt: ViewGroundTruth, iou_threshold: float) -> np.ndarray:
    """One-to-one class-aware greedy matching: (P,) int, the ground truth each prediction matched
    (-1: none)."""
    P, G = len(det.boxes), len(gt.boxes)
    pairs = np.full(P, -1, dtype=np.int64)
    if P == 0 or G == 0:
        return pairs
    taken = np.zeros(G, dtype=bool)
    iou = box_iou(det.boxes, gt.boxes)
    iou = np.where(np.asarray(det.classes)[:, None] == np.asarray(gt.classes)[None, :], iou, -1.0)
    for p in np.argsort(-np.asarray(det.scores), kind="stable"):
        cand = np.where(taken, -1.0, iou[p])
        g = int(np.argmax(cand))
        if cand[g] >= iou_threshold:
            pairs[p], taken[g] = g, True
    return pairs


def match_strict(det: ViewDetections, gt: ViewGroundTruth, iou_threshold: float):
    """One-to-one class-aware greedy matching. Returns (det_matched (P,) bool, gt_matched (G,) bool)."""
    pairs = strict_pairs(det, gt, iou_threshold)
    gt_m = np.zeros(len(gt.boxes), dtype=bool)
    gt_m[pairs[pairs >= 0]] = True
    return pairs >= 0, gt_m


def as_boxes(b) -> np.ndarray:
    return np.zeros((0, 4)) if b is None else np.asarray(b, dtype=np.float64).reshape(-1, 4)


def best_iou(boxes: np.ndarray, others: np.ndarray) -> np.ndarray:
    """(P,) each box's highest IoU with ``others`` (0 when there are none)."""
    return box_iou(boxes, others).max(axis=1) if len(boxes) and len(others) else np.zeros(len(boxes))


def ignored_predictions(det: ViewDetections, gt: ViewGroundTruth, det_matched: np.ndarray,
                        iou_threshold: float) -> np.ndarray:
    """(P,) bool: predictions the one-to-one matching left unmatched that cover an excluded road user
    of their class, intersection over the prediction's own area >= the threshold: neither TP nor FP in
    strict counting and AP. This is COCOeval's rule for crowd regions (the COCO export's ``iscrowd``
    boxes), so AP50 agrees with COCOeval on the same ground truth (see the module docstring)."""
    boxes, regions = as_boxes(det.boxes), as_boxes(gt.excluded_boxes)
    unmatched = ~np.asarray(det_matched, dtype=bool)
    if len(boxes) == 0 or len(regions) == 0:
        return np.zeros(len(boxes), dtype=bool)
    lt = np.maximum(boxes[:, None, :2], regions[None, :, :2])
    rb = np.minimum(boxes[:, None, 2:], regions[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0, None), axis=-1)
    area = box_area(boxes)[:, None]
    cover = np.where(area > 0, inter / np.where(area > 0, area, 1), 0.0)
    if gt.excluded_classes is not None:
        cover = np.where(np.asarray(det.classes)[:, None] == np.asarray(gt.excluded_classes)[None, :], cover, 0.0)
    return unmatched & (cover.max(axis=1) >= iou_threshold)


def precision_recall_ap(scores, tps, n_gt: int) -> float:
    """COCO's 101-point interpolated AP of detections (``scores``, each a TP or not) against ``n_gt``
    ground-truth objects."""
    order = np.argsort(-np.asarray(scores), kind="stable")
    tp = np.asarray(tps, dtype=float)[order]
    ctp, cfp = np.cumsum(tp), np.cumsum(1 - tp)
    recall = ctp / n_gt
    precision = ctp / np.maximum(ctp + cfp, 1e-12)
    precision = np.maximum.accumulate(precision[::-1])[::-1] if len(precision) else precision
    ap = 0.0
    for r in np.linspace(0, 1, 101):
        above = precision[recall >= r]
        ap += (above.max() if above.size else 0.0) / 101
    return ap
