"""Metrics on the ground plane, for detections with a 3D centre (bev, late fusion, lifted 2D ones).

Per scored view, the view's ground truth (the road users labelled there) against the detections
that view reports, both by their world box centres; distances are on the ground plane (x, y):

* **centre-distance AP** (nuScenes): per class, detections by descending score matched to the
  nearest unmatched ground truth of their class within d metres (d = 0.5, 1, 2, 4); precision
  at 101 recall points (the best precision at that recall or above, as COCO interpolates), the
  part above recall 0.1 and precision 0.1 averaged and rescaled as nuScenes' ``calc_ap`` does;
  mean over classes with ground truth;
* **MODA / MODP** (CLEAR MOT, as MVDet reports them): per view and class a minimum-cost
  one-to-one assignment (Hungarian) of detections to ground truth within r metres (0.5 for
  pedestrians, 1 for other classes; ``matches_within``, shared with the field's file evaluation in
  ``ground_moda``); MODA = 1 - (FP + FN) / ground truth, MODP = mean of 1 - d / r over the matches;
* **recall within 1 m** (MODA's matching at 1 m for every class), split by the target view's
  visibility like the 2D recall groups: all, fully hidden in the view, hidden-but-seen.

A detection unmatched but within the distance of a labelled road user left out of the ground
truth (``ViewGroundTruth.excluded_centres``) is ignored, as in 2D.

Example::

    summary = metrics_3d(acc.records, ["car", "pedestrian"])   # None when no detection has a centre
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from pnyolo.evaluation.matching import ViewDetections, ViewGroundTruth

AP_DISTANCES = (0.5, 1.0, 2.0, 4.0)
MODA_RADIUS = {"pedestrian": 0.5}  # metres; other classes 1.0
DEFAULT_RADIUS = 1.0
RECALL_RADIUS = 1.0
MIN_RECALL = MIN_PRECISION = 0.1


def ground_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P, G) distances on the ground plane between centres a (P, 3) and b (G, 3)."""
    a, b = np.asarray(a, dtype=np.float64).reshape(-1, 3), np.asarray(b, dtype=np.float64).reshape(-1, 3)
    return np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])


def hungarian(cost: np.ndarray) -> list[tuple[int, int]]:
    """Minimum-cost assignment of a (n, m) cost matrix: (row, column) pairs, min(n, m) of them, sorted
    (scipy's ``linear_sum_assignment``)."""
    rows, cols = linear_sum_assignment(np.asarray(cost, dtype=np.float64))
    return sorted(zip(rows.tolist(), cols.tolist()))


def matches_within(d: np.ndarray, radius: float) -> list[tuple[int, int, float]]:
    """The minimum-cost one-to-one matching of a (P, G) distance matrix, pairs farther than
    ``radius`` barred (one exactly at it matches, as CLEAR MOD's published evaluators count):
    (row, column, distance), sorted."""
    d = np.asarray(d, dtype=np.float64)
    if d.size == 0:
        return []
    return [(a, b, float(d[a, b])) for a, b in hungarian(np.where(d <= radius, d, 1e6)) if d[a, b] <= radius]


def _has_centres(det: ViewDetections) -> bool:
    return det.centres is not None and (len(det.boxes) == 0 or bool(np.isfinite(det.centres).all()))


def _ignored(det_xyz: np.ndarray, matched: np.ndarray, gt: ViewGroundTruth, radius: float) -> np.ndarray:
    """Unmatched detections within ``radius`` of no ground truth but of an excluded road user."""
    near_gt = (ground_distances(det_xyz, gt.centres) < radius).any(axis=1) if len(gt.boxes) else np.zeros(len(det_xyz), bool)
    ex = gt.excluded_centres
    near_ex = (ground_distances(det_xyz, ex) < radius).any(axis=1) if ex is not None and len(ex) else \
        np.zeros(len(det_xyz), bool)
    return ~matched & ~near_gt & near_ex


def greedy_centre_match(det: ViewDetections, gt: ViewGroundTruth, radius: float, cls: int) -> tuple[np.ndarray, np.ndarray]:
    """One class's detections by descending score, each to the nearest unmatched ground truth of
    the class within ``radius``: (scores, matched) of the detections not ignored."""
    dm, gm = np.asarray(det.classes) == cls, np.asarray(gt.classes) == cls
    xyz, scores = np.asarray(det.centres)[dm], np.asarray(det.scores)[dm]
    gxyz = np.asarray(gt.centres).reshape(-1, 3)[gm]
    d = ground_distances(xyz, gxyz)
    matched, taken = np.zeros(len(xyz), bool), np.zeros(len(gxyz), bool)
    for p in np.argsort(-scores, kind="stable"):
        if not len(gxyz):
            break
        cand = np.where(taken, np.inf, d[p])
        g = int(np.argmin(cand))
        if cand[g] < radius:
            matched[p], taken[g] = True, True
    keep = ~_ignored(xyz, matched, gt, radius)
    return scores[keep], matched[keep]


def nuscenes_ap(scores: np.ndarray, matched: np.ndarray, n_gt: int) -> float:
    """nuScenes' AP from the detections' scores and whether each matched, with ``n_gt`` ground truths."""
    if n_gt == 0:
        return float("nan")
    order = np.argsort(-scores, kind="stable")
    tp = np.cumsum(matched[order].astype(np.float64))
    fp = np.cumsum(~matched[order])
    if not len(tp):
        return 0.0
    recall, precision = tp / n_gt, tp / np.maximum(tp + fp, 1e-12)
    points = np.linspace(0, 1, 101)
    prec = np.array([precision[recall >= r].max() if (recall >= r).any() else 0.0 for r in points])
    prec = prec[int(round(100 * MIN_RECALL)) + 1:] - MIN_PRECISION
    return float(np.clip(prec, 0, None).mean() / (1 - MIN_PRECISION))


def assignment(det: ViewDetections, gt: ViewGroundTruth, radius_of) -> tuple[list[tuple[int, int, float]], np.ndarray]:
    """Per class, the Hungarian assignment of detections to ground truth within its radius:
    (det index, gt index, distance) matches, and which detections are ignored (P,) bool."""
    matches, ignored = [], np.zeros(len(det.boxes), bool)
    for c in np.unique(np.concatenate([np.asarray(det.classes), np.asarray(gt.classes)]).astype(np.int64)):
        r = radius_of(int(c))
        di, gi = np.where(np.asarray(det.classes) == c)[0], np.where(np.asarray(gt.classes) == c)[0]
        d = ground_distances(np.asarray(det.centres)[di], np.asarray(gt.centres).reshape(-1, 3)[gi])
        found = [(di[a], gi[b], dist) for a, b, dist in matches_within(d, r)]
        matches += found
        hit = np.zeros(len(di), bool)
        hit[[np.where(di == p)[0][0] for p, _, _ in found]] = True
        ignored[di] = _ignored(np.asarray(det.centres)[di], hit, gt, r)
    return matches, ignored


def metrics_3d(records: list[tuple[ViewDetections, ViewGroundTruth]], class_names: list[str],
               distances=AP_DISTANCES) -> dict | None:
    """The module docstring's metrics over (detections, ground truth) of views; None when the
    detections have no world centres (a model without 3D outputs)."""
    if not records or not all(_has_centres(d) for d, _ in records) or any(g.centres is None for _, g in records):
        return None
    out: dict = {"ap": {}}
    for dist in distances:
        per_class = {}
        for c, name in enumerate(class_names):
            parts = [greedy_centre_match(d, g, dist, c) for d, g in records]
            n_gt = sum(int((np.asarray(g.classes) == c).sum()) for _, g in records)
            scores = np.concatenate([s for s, _ in parts]) if parts else np.zeros(0)
            matched = np.concatenate([m for _, m in parts]).astype(bool) if parts else np.zeros(0, bool)
            per_class[name] = nuscenes_ap(scores, matched, n_gt)
        valid = [v for v in per_class.values() if np.isfinite(v)]
        out["ap"][f"{dist:g}"] = {"mean": float(np.mean(valid)) if valid else None,
                                  **{k: (None if not np.isfinite(v) else v) for k, v in per_class.items()}}
    tp = fp = fn = 0
    closeness = []
    for det, gt in records:
        matches, ignored = assignment(det, gt, lambda c: MODA_RADIUS.get(class_names[c], DEFAULT_RADIUS))
        tp += len(matches)
        fp += int((~ignored).sum()) - len(matches)
        fn += len(gt.boxes) - len(matches)
        closeness += [1 - d / MODA_RADIUS.get(class_names[int(gt.classes[g])], DEFAULT_RADIUS) for _, g, d in matches]
    n_gt = tp + fn
    out["moda"] = 1 - (fp + fn) / n_gt if n_gt else None
    out["modp"] = float(np.mean(closeness)) if closeness else None
    out["counts"] = {"tp": tp, "fp": fp, "fn": fn}
    groups = {"all": [0, 0], "fully hidden in the target view": [0, 0], "hidden here, seen in another view": [0, 0]}
    for det, gt in records:
        matches, _ = assignment(det, gt, lambda c: RECALL_RADIUS)
        hit = np.zeros(len(gt.boxes), bool)
        hit[[g for _, g, _ in matches]] = True
        hidden = np.asarray(gt.visible_fraction) <= 1e-6
        for name, mask in (("all", np.ones(len(hit), bool)), ("fully hidden in the target view", hidden),
                           ("hidden here, seen in another view", hidden & np.asarray(gt.seen_elsewhere, bool))):
            groups[name][0] += int(hit[mask].sum())
            groups[name][1] += int(mask.sum())
    out[f"recall_within_{RECALL_RADIUS:g}m"] = {k: {"recall": h / n if n else None, "n": n} for k, (h, n) in groups.items()}
    return out
