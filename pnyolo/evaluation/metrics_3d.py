"""Metrics on the ground plane, for detections with a 3D centre (bev, late fusion, lifted 2D ones).

Per scored view, the view's ground truth (the road users labelled there) against the detections
that view reports, both by their world box centres; distances are on the ground plane (x, y):

* **the nuScenes devkit's detection metrics** (``nuscenes_metrics``): mAP over centre distances of 0.5, 1,
  2 and 4 m and the NDS with its true-positive errors, by the devkit's own algorithm functions;
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
from pnyolo.evaluation.nuscenes_metrics import per_view_metrics

MODA_RADIUS = {"pedestrian": 0.5}  # metres; other classes 1.0
DEFAULT_RADIUS = 1.0
RECALL_RADIUS = 1.0


def ground_ap(summary_3d: dict | None, distance: str = "1") -> float | None:
    """The mean per-view AP within ``distance`` metres of a ``metrics_3d`` summary (older summaries keyed it
    ``devkit``); None where there is none."""
    m3 = summary_3d or {}
    return (((m3.get("per_view") or m3.get("devkit") or {}).get("ap", {}).get(distance)) or {}).get("mean")


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


def metrics_3d(records: list[tuple[ViewDetections, ViewGroundTruth]], class_names: list[str]) -> dict | None:
    """The module docstring's metrics over (detections, ground truth) of views; None when the
    detections have no world centres (a model without 3D outputs)."""
    if not records or not all(_has_centres(d) for d, _ in records) or any(g.centres is None for _, g in records):
        return None
    out: dict = {"per_view": per_view_metrics(records, class_names)}
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
