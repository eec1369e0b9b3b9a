"""Where a detector's placement goes wrong: each matched detection's ground-plane error split along the line of sight
from the nearest camera (depth) and across it (lateral), by distance from that camera.

A camera measures direction well and depth badly, so a detector that lifts image features without knowing depth
smears a road user along the ray: its error is radial and grows with distance. A grid too coarse, or a heatmap too
wide, errs in every direction alike, about cell / sqrt(12) a side. The split tells the two apart (issue 87, the
placement probe). Matching is the nuScenes devkit's rule for its true-positive errors: predictions in descending
score, each taking the nearest unmatched ground truth of its sample and class within ``radius`` (2 m)::

    pairs = greedy_matches(pred_xy, scores, gt_xy, radius=2.0)          # [(prediction, ground truth)]
    radial, lateral, distance = decompose(pred_xy[p], gt_xy[g], camera_xy)
    rows = placement_rows(radial, lateral, distance, layouts)           # per distance bin, standard errors over layouts
    figures = placement_of("out/dataset", "test", results_doc)           # all of it on nuScenes results, per class
"""
from __future__ import annotations

import contextlib
import io
import json
import tempfile
from pathlib import Path

import numpy as np

from pnyolo.evaluation.bootstrap import draws_of

BINS_M = (0.0, 10.0, 20.0, 30.0, float("inf"))  # distance from the nearest camera


def greedy_matches(pred_xy: np.ndarray, scores: np.ndarray, gt_xy: np.ndarray, radius: float) -> list[tuple[int, int]]:
    """The devkit's matching of one sample and class: predictions (P, 2) by descending score (ties by position), each to
    the nearest unmatched ground truth (G, 2) within ``radius`` metres; (prediction, ground truth) pairs."""
    pred_xy, gt_xy = np.asarray(pred_xy, float).reshape(-1, 2), np.asarray(gt_xy, float).reshape(-1, 2)
    taken = np.zeros(len(gt_xy), dtype=bool)
    pairs = []
    for p in np.argsort(-np.asarray(scores, float), kind="stable"):
        if taken.all():
            break
        d = np.hypot(*(gt_xy - pred_xy[p]).T)
        d[taken] = np.inf
        g = int(np.argmin(d)) if len(d) else -1
        if g >= 0 and d[g] <= radius:
            taken[g] = True
            pairs.append((int(p), g))
    return pairs


def decompose(pred_xy: np.ndarray, gt_xy: np.ndarray, cameras_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Errors of predictions (N, 2) against their ground truth (N, 2), each split along the ray from the camera nearest
    its ground truth among ``cameras_xy`` (C, 2): radial (positive: placed farther than it is), lateral (signed, to
    the ray's left) and that camera's distance, each (N,)."""
    pred_xy, gt_xy = np.asarray(pred_xy, float).reshape(-1, 2), np.asarray(gt_xy, float).reshape(-1, 2)
    cams = np.asarray(cameras_xy, float).reshape(-1, 2)
    if not len(cams):
        raise ValueError("decompose: no camera to measure the line of sight from")
    to_gt = gt_xy[:, None, :] - cams[None, :, :]
    nearest = np.argmin(np.hypot(to_gt[..., 0], to_gt[..., 1]), axis=1)
    ray = to_gt[np.arange(len(gt_xy)), nearest]
    distance = np.hypot(ray[:, 0], ray[:, 1])
    unit = ray / np.maximum(distance, 1e-9)[:, None]
    err = pred_xy - gt_xy
    radial = (err * unit).sum(axis=1)
    lateral = unit[:, 0] * err[:, 1] - unit[:, 1] * err[:, 0]
    return radial, lateral, distance


def _rms(v: np.ndarray) -> float:
    return float(np.sqrt(np.mean(v * v))) if len(v) else float("nan")


def _share_se(radial: np.ndarray, lateral: np.ndarray, layouts: np.ndarray) -> float | None:
    """The bootstrap standard error (layouts resampled) of the squared error's share along the ray."""
    names = sorted(set(layouts.tolist()))
    if len(names) < 2:
        return None
    r2 = np.array([(radial[layouts == n] ** 2).sum() for n in names])
    t2 = r2 + np.array([(lateral[layouts == n] ** 2).sum() for n in names])
    draws = draws_of(len(names))
    return float(np.std(r2[draws].sum(axis=1) / np.maximum(t2[draws].sum(axis=1), 1e-12)))


def placement_rows(radial: np.ndarray, lateral: np.ndarray, distance: np.ndarray, layouts: np.ndarray,
                   bins=BINS_M) -> list[dict]:
    """Per distance bin (and all): matches, median distance error, RMS radial and lateral error, the mean radial error
    (bias), and the squared error's share along the ray with its standard error over ``layouts`` (N,) names."""
    radial, lateral, distance = (np.asarray(v, float) for v in (radial, lateral, distance))
    layouts = np.asarray(layouts)
    edges = list(zip(bins[:-1], bins[1:])) + [(bins[0], bins[-1])]
    rows = []
    for lo, hi in edges:
        m = (distance >= lo) & (distance < hi)
        r, t = radial[m], lateral[m]
        total = float((r * r).sum() + (t * t).sum())
        rows.append({"bin": f"{lo:g}-{hi:g} m" if np.isfinite(hi) else (f"{lo:g}+ m" if (lo, hi) != edges[-1] else "all"),
                     "n": int(m.sum()), "median_error_m": float(np.median(np.hypot(r, t))) if m.any() else None,
                     "rms_radial_m": _rms(r) if m.any() else None, "rms_lateral_m": _rms(t) if m.any() else None,
                     "mean_radial_m": float(r.mean()) if m.any() else None,
                     "radial_share": float((r * r).sum() / total) if total > 0 else None,
                     "radial_share_se": _share_se(r, t, layouts[m]) if m.any() else None})
    return rows


def duplicates(xy: np.ndarray, scores: np.ndarray, radius: float) -> int:
    """How many of one sample-and-class's predictions (N, 2) lie within ``radius`` metres of a higher-scoring one: what
    a suppression by centre distance would remove."""
    xy, scores = np.asarray(xy, float).reshape(-1, 2), np.asarray(scores, float)
    d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    higher = scores[None, :] > scores[:, None]
    return int(((d <= radius) & higher).any(axis=1).sum())


def _cameras(nusc, sample: dict) -> np.ndarray:
    """(C, 2) world x, y of a devkit sample's cameras (ego pose composed with the sensor's calibration)."""
    from pyquaternion import Quaternion

    xy = []
    for channel, sd_token in sample["data"].items():
        if channel.startswith("CAM_"):
            sd = nusc.get("sample_data", sd_token)
            cs, ep = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"]), nusc.get("ego_pose", sd["ego_pose_token"])
            xy.append((Quaternion(ep["rotation"]).rotation_matrix @ np.asarray(cs["translation"]) + ep["translation"])[:2])
    return np.asarray(xy).reshape(-1, 2)


def _decomposed(nusc, kit, names: list[str], radius: float, dup_radius: float) -> dict:
    """Per class the decomposed errors of every match of the devkit's loaded boxes, their layouts, the duplicates."""
    from dataset_spec.splits import layout_of

    out = {c: {"radial": [], "lateral": [], "distance": [], "layout": [], "predictions": 0, "duplicates": 0,
               "ground_truth": 0} for c in names}
    for token in kit.gt_boxes.sample_tokens:
        sample = nusc.get("sample", token)
        cams = _cameras(nusc, sample)
        layout = layout_of(nusc.get("scene", sample["scene_token"])["name"].rsplit("__", 1)[0])
        for c in names:
            preds = [b for b in kit.pred_boxes[token] if b.detection_name == c]
            gxy = np.array([b.translation[:2] for b in kit.gt_boxes[token] if b.detection_name == c]).reshape(-1, 2)
            pxy, scores = np.array([b.translation[:2] for b in preds]).reshape(-1, 2), np.array([b.detection_score for b in preds])
            o = out[c]
            o["predictions"], o["ground_truth"] = o["predictions"] + len(preds), o["ground_truth"] + len(gxy)
            o["duplicates"] += duplicates(pxy, scores, dup_radius)
            pairs = greedy_matches(pxy, scores, gxy, radius)
            if pairs and len(cams):
                p, g = (np.array(v) for v in zip(*pairs))
                for key, values in zip(("radial", "lateral", "distance"), decompose(pxy[p], gxy[g], cams)):
                    o[key] += values.tolist()
                o["layout"] += [layout] * len(p)
    return out


def placement_of(dataset_root, split: str, doc: dict, radius: float = 2.0, dup_radius: float = 1.0) -> dict:
    """Nuscenes results ``doc`` on ``split`` of the dataset, matched as the devkit's DetectionEval matches for its
    true-positive errors (on the split's export with buses and trucks as cars, every lighting; its ranges and point
    filter): per class (car, pedestrian) the counts, ``placement_rows`` and every match's decomposed error."""
    from nuscenes.eval.detection.config import config_factory
    from nuscenes.eval.detection.evaluate import DetectionEval
    from nuscenes.nuscenes import NuScenes

    from dataset_spec.nuscenes_format import SPLIT_NAMES, VERSION
    from pnyolo.evaluation.devkit_eval import NAMED, complete_results, export_split

    with tempfile.TemporaryDirectory(prefix="placement-") as tmp:
        export = export_split(dataset_root, split, Path(tmp) / "named", "all", refined=False)
        path = Path(tmp) / "results.json"
        path.write_text(json.dumps(complete_results(doc, export, split)[0]))
        cfg = config_factory("detection_cvpr_2019")
        cfg.class_names = list(NAMED)
        with contextlib.redirect_stdout(io.StringIO()):
            nusc = NuScenes(version=VERSION, dataroot=str(export), verbose=False)
            kit = DetectionEval(nusc, cfg, str(path), SPLIT_NAMES[split], str(Path(tmp) / "kit"), verbose=False)
        raw = _decomposed(nusc, kit, list(NAMED), radius, dup_radius)
    return {c: {"predictions": o["predictions"], "ground_truth": o["ground_truth"], "duplicates": o["duplicates"],
                "matches": len(o["radial"]), "rows": placement_rows(o["radial"], o["lateral"], o["distance"], o["layout"]),
                "points": {k: o[k] for k in ("radial", "lateral", "distance")}} for c, o in raw.items()}
