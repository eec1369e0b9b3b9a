"""The nuScenes devkit's detection metrics on our ground plane: its own ``accumulate``, ``calc_ap`` and ``calc_tp``
(nuscenes-devkit 1.2.0, ``detection_cvpr_2019``: centre distance, thresholds 0.5 / 1 / 2 / 4 m, true-positive
errors at 2 m, recall and precision from 0.1) on ``EvalBoxes`` built from our splits, since its own loaders
only know nuScenes' scenes::

    summary = per_view_metrics(records, ["car", "pedestrian"])   # {"ap": {...}, "map", "nds", "errors": {...}}

Each scored view is one devkit sample: the road users labelled there against the detections the view reports,
by world box. A detection within a threshold of a labelled road user left out of the ground truth (too far, too
truncated) and of no ground truth is left out at that threshold (our ignore rule, as in 2D). Ground truth carries
its 3D box, its velocity on sequences (NaN on one frame) and its attribute from the motion; detections their
world box where the model has one (bev, late fusion; sizes and yaw of 1 m and 0 otherwise, whose scale and
orientation errors are then not reported), velocities and attributes where they state them (results files; a
model that predicts none stands still without an attribute, and the devkit counts the errors that leaves). mAP is the mean over our classes with ground truth and the four thresholds; NDS = (5 mAP + the sum over ATE, ASE, AOE,
AVE, AAE of max(0, 1 - error)) / 10, an error the devkit cannot measure counting 0 (as its own NDS does).
"""
from __future__ import annotations

import math

import numpy as np

from dataset_spec.nuscenes_format import attribute_of, yaw_quaternion
from pnyolo.evaluation.matching import ViewDetections, ViewGroundTruth

ERRORS = {"trans_err": "ATE", "scale_err": "ASE", "orient_err": "AOE", "vel_err": "AVE", "attr_err": "AAE"}
SCALE_FREE = ("scale_err", "orient_err")  # need a predicted box: not reported for centres alone


def devkit():
    """The devkit's pieces (a one-line error where it is not installed: it needs numpy<2)."""
    try:
        from nuscenes.eval.common.data_classes import EvalBoxes
        from nuscenes.eval.common.utils import center_distance
        from nuscenes.eval.detection.algo import accumulate, calc_ap, calc_tp
        from nuscenes.eval.detection.config import config_factory
        from nuscenes.eval.detection.constants import DETECTION_NAMES
        from nuscenes.eval.detection.data_classes import DetectionBox
    except ImportError:
        return None
    return {"EvalBoxes": EvalBoxes, "DetectionBox": DetectionBox, "accumulate": accumulate, "calc_ap": calc_ap,
            "calc_tp": calc_tp, "center_distance": center_distance, "config": config_factory("detection_cvpr_2019"),
            "names": DETECTION_NAMES}


def _box(kit, sample: str, centre, box, name: str, score: float | None = None, velocity=(np.nan, np.nan),
         attribute: str = ""):
    if box is None:
        size, yaw = (1.0, 1.0, 1.0), 0.0
    else:
        size, yaw = (float(box[4]), float(box[3]), float(box[5])), float(box[6])  # nuScenes: width, length, height
    return kit["DetectionBox"](sample_token=sample, translation=tuple(float(v) for v in centre), size=size,
                               rotation=tuple(yaw_quaternion(yaw)), velocity=tuple(float(v) for v in velocity),
                               detection_name=name, detection_score=-1.0 if score is None else float(score),
                               attribute_name=attribute)


def _gt_boxes(kit, records, class_names: list[str]):
    boxes = kit["EvalBoxes"]()
    for k, (_, gt) in enumerate(records):
        rows = []
        for g in range(len(gt.boxes)):
            name = class_names[int(gt.classes[g])]
            if name not in kit["names"]:
                continue
            v = gt.velocities[g] if gt.velocities is not None else (np.nan, np.nan)
            speed = None if not np.isfinite(v).all() else float(np.hypot(*v))
            rows.append(_box(kit, f"view{k}", gt.centres[g], None if gt.world_boxes is None else gt.world_boxes[g],
                             name, velocity=v, attribute=attribute_of(name, speed, False)))
        boxes.add_boxes(f"view{k}", rows)
    return boxes


def _pred_boxes(kit, records, class_names: list[str], threshold: float):
    """The detections, those our ignore rule leaves out at ``threshold`` left out."""
    boxes = kit["EvalBoxes"]()
    for k, (det, gt) in enumerate(records):
        xy = np.asarray(det.centres, dtype=np.float64).reshape(-1, 3)[:, :2]
        near_gt = _near(xy, gt.centres, threshold)
        near_ex = _near(xy, gt.excluded_centres, threshold)
        rows = [_box(kit, f"view{k}", det.centres[p], None if det.world_boxes is None else det.world_boxes[p],
                     class_names[int(det.classes[p])], det.scores[p],
                     velocity=(0.0, 0.0) if det.velocities is None else det.velocities[p],
                     attribute="" if det.attributes is None else det.attributes[p])
                for p in range(len(det.scores)) if class_names[int(det.classes[p])] in kit["names"]
                and not (near_ex[p] and not near_gt[p])]
        boxes.add_boxes(f"view{k}", rows)
    return boxes


def _near(xy: np.ndarray, centres, threshold: float) -> np.ndarray:
    if centres is None or not len(centres) or not len(xy):
        return np.zeros(len(xy), bool)
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)[:, :2]
    return (np.hypot(xy[:, None, 0] - c[None, :, 0], xy[:, None, 1] - c[None, :, 1]) < threshold).any(axis=1)


def per_view_metrics(records: list[tuple[ViewDetections, ViewGroundTruth]], class_names: list[str]) -> dict | None:
    """mAP per threshold and class, the true-positive errors and NDS by the devkit (the module docstring); None
    when the devkit is missing or no class is one of its detection names."""
    kit = devkit()
    present = {class_names[int(c)] for _, gt in records for c in gt.classes}
    names = [c for c in class_names if kit is not None and c in kit["names"] and c in present]  # with ground truth
    if kit is None:
        return None
    if not names:
        return {"ap": {f"{d:g}": {"mean": None} for d in kit["config"].dist_ths}, "map": None,
                "errors": {e: None for e in ERRORS.values()}, "nds": None, "classes": []}
    cfg, gt = kit["config"], _gt_boxes(kit, records, class_names)
    with_boxes = all(det.world_boxes is not None for det, _ in records)
    ap, errors = {}, {m: [] for m in ERRORS}
    for dist in cfg.dist_ths:
        preds = _pred_boxes(kit, records, class_names, dist)
        per_class = {}
        for name in names:
            md = kit["accumulate"](gt, preds, name, kit["center_distance"], dist)
            per_class[name] = kit["calc_ap"](md, cfg.min_recall, cfg.min_precision)
            if dist == cfg.dist_th_tp:
                for m in ERRORS:
                    errors[m].append(kit["calc_tp"](md, cfg.min_recall, m))
        ap[f"{dist:g}"] = {"mean": float(np.mean(list(per_class.values()))), **per_class}
    mean_ap = float(np.mean([v["mean"] for v in ap.values()]))
    err = {ERRORS[m]: _nanmean(v) for m, v in errors.items()}
    if not with_boxes:
        err.update({ERRORS[m]: None for m in SCALE_FREE})
    scores = [max(0.0, 1.0 - e) if e is not None else 0.0 for e in err.values()]
    return {"ap": ap, "map": mean_ap, "errors": err, "nds": (cfg.mean_ap_weight * mean_ap + sum(scores)) / 10.0,
            "classes": names}


def _nanmean(values: list[float]) -> float | None:
    finite = [v for v in values if v is not None and not math.isnan(v)]
    return float(np.mean(finite)) if finite else None
