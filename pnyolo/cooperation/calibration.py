"""Late fusion's scores calibrated per sender: the chance that a car's detection is a road user, given its
score and how far it lies from that car's camera, fitted on validation by logistic regression::

    coef = fit_calibration(scores, distances, labels)        # on validation reports (``report_labels``)
    cars = calibrated(cars, item, coef)                      # what the receiver fuses

One car's own-view detections are good near its camera and poor far away (the cpu_seq report: bev own view
F1@0.2 0.59 within 13 m, 0.14 beyond 25 m), while its raw scores say little of that. The calibrated score
is ``sigmoid(a * logit(s) + b * d / 10 m + c)`` with ``d`` the ground distance from the sender's camera;
the noisy-OR of agreement (``pnyolo.cooperation.agreement``) then combines chances rather than scores.
"""
from __future__ import annotations

import numpy as np

from pnyolo.decoding.detections import WorldDetections

DISTANCE_UNIT_M = 10.0  # distances enter the regression in tens of metres (coefficients of one order)
# L2 weight on the coefficients: a fit on (nearly) separated reports stays of the features' order (at 1e-3 one ran
# to 8.7e6 on pixelNeRF-YOLO's validation reports), while against thousands of reports it moves a fit by little
RIDGE = 1.0


def _features(scores: np.ndarray, distances: np.ndarray) -> np.ndarray:
    s = np.clip(np.asarray(scores, np.float64), 1e-4, 1 - 1e-4)
    return np.stack([np.log(s / (1 - s)), np.asarray(distances, np.float64) / DISTANCE_UNIT_M, np.ones(len(s))], 1)


def fit_calibration(scores: np.ndarray, distances: np.ndarray, labels: np.ndarray, steps: int = 50) -> tuple:
    """(a, b, c) of the logistic regression of ``labels`` (1: a true road user) on the reports' scores and
    distances (metres), by Newton's method with a small ridge; (1, 0, 0), the scores as they are, without
    both kinds of label."""
    y = np.asarray(labels, np.float64)
    if len(y) == 0 or y.min() == y.max():
        return (1.0, 0.0, 0.0)
    x = _features(scores, distances)
    w = np.array([1.0, 0.0, 0.0])
    for _ in range(steps):
        p = 1 / (1 + np.exp(-x @ w))
        grad = x.T @ (p - y) + RIDGE * w
        hess = (x * (p * (1 - p))[:, None]).T @ x + RIDGE * np.eye(3)
        step = np.linalg.solve(hess, grad)
        w -= step
        if np.abs(step).max() < 1e-9:
            break
    return tuple(float(v) for v in w)


def calibrate_scores(scores: np.ndarray, distances: np.ndarray, coef) -> np.ndarray:
    """The chance each report is a road user, by ``coef`` from ``fit_calibration``."""
    return 1 / (1 + np.exp(-_features(scores, distances) @ np.asarray(coef, np.float64)))


def sender_distances(item, b: int, dets: WorldDetections) -> np.ndarray:
    """Ground distance (metres) from view ``b``'s camera to each detection's centre."""
    eye = item.camera_to_world[b, :2, 3].double().numpy()
    return np.hypot(*(dets.boxes[:, :2] - eye).T) if len(dets) else np.zeros(0)


def calibrated(cars: list[WorldDetections], item, coef) -> list[WorldDetections]:
    """Each view's car's detections (``cars[b]`` from view ``b``) with calibrated scores (``coef`` None: as
    they are)."""
    if coef is None:
        return cars
    return [WorldDetections(d.boxes, calibrate_scores(d.scores, sender_distances(item, b, d), coef), d.classes)
            if len(d) else d for b, d in enumerate(cars)]


def report_labels(dets: WorldDetections, item, radius: float) -> np.ndarray:
    """1 for each detection that is a road user of the item's 3D ground truth (same class, ground centre within
    ``radius`` metres, each road user claimed once, by the best-scoring detection first), else 0."""
    labels = np.zeros(len(dets), np.float64)
    if item.boxes_3d is None or not len(dets):
        return labels
    truth = item.boxes_3d.double().numpy()[:, :2]
    classes = item.box_classes.numpy()
    free = np.ones(len(truth), bool)
    for i in np.argsort(-dets.scores, kind="stable"):
        gap = np.hypot(*(truth - dets.boxes[i, :2]).T)
        gap[~free | (classes != dets.classes[i])] = np.inf
        j = int(np.argmin(gap)) if len(gap) else -1
        if j >= 0 and gap[j] < radius:
            free[j], labels[i] = False, 1.0
    return labels
