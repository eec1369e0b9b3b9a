"""YOLO anchors fitted to a dataset's training labels (k-means on box width/height under IoU).

Example::

    anchors = anchors_from_labels(ds, ds.split("train"), k=3)    # [[w, h], ...] image fractions
    load_config("configs/cpu.yaml", [f"model.head.anchors={anchors}"])

Boxes are compared by the IoU of their (w, h) when centred on each other, the measure YOLO uses
to assign a ground-truth box to its best anchor, so the fitted anchors match that assignment.
"""
from __future__ import annotations

import numpy as np

from dataset_spec import Dataset, LabelThresholds


def wh_iou(wh: np.ndarray, anchors: np.ndarray) -> np.ndarray:
    """IoU of centred boxes: wh (N, 2) x anchors (K, 2) -> (N, K)."""
    inter = np.minimum(wh[:, None, 0], anchors[None, :, 0]) * np.minimum(wh[:, None, 1], anchors[None, :, 1])
    return inter / (wh[:, None].prod(-1) + anchors[None].prod(-1) - inter)


def kmeans_anchors(wh: np.ndarray, k: int, seed: int = 0, iterations: int = 100) -> np.ndarray:
    """k anchors (k, 2) sorted by area, maximising the mean best IoU with ``wh`` (N, 2)."""
    wh = np.asarray(wh, dtype=np.float64).reshape(-1, 2)
    wh = wh[(wh > 0).all(axis=1)]
    if len(wh) < k:
        raise ValueError(f"need at least {k} boxes to fit {k} anchors, got {len(wh)}")
    rng = np.random.default_rng(seed)
    # k-means++ style start: spread the initial anchors over the data
    anchors = wh[[rng.integers(len(wh))]]
    while len(anchors) < k:
        d = 1.0 - wh_iou(wh, anchors).max(axis=1)
        anchors = np.vstack([anchors, wh[rng.choice(len(wh), p=d / d.sum()) if d.sum() > 0 else rng.integers(len(wh))]])
    for _ in range(iterations):
        assign = wh_iou(wh, anchors).argmax(axis=1)
        new = np.array([np.median(wh[assign == j], axis=0) if np.any(assign == j) else anchors[j] for j in range(k)])
        if np.allclose(new, anchors):
            break
        anchors = new
    return anchors[np.argsort(anchors.prod(axis=1))]


def label_sizes(ds: Dataset, scenarios: list[str], classes: list[str] | None = None,
                thresholds: LabelThresholds | None = None) -> np.ndarray:
    """(N, 2) widths and heights, as fractions of the image, of the kept labels of ``scenarios``."""
    out = []
    for s in scenarios:
        for cam in ds.scenario(s).cameras:
            labels = ds.read_labels(s, cam.name)
            for o in labels.kept(thresholds):
                if classes is None or o.cls in classes:
                    out.append(((o.box[2] - o.box[0]) / labels.width, (o.box[3] - o.box[1]) / labels.height))
    return np.array(out, dtype=np.float64).reshape(-1, 2)


def anchors_from_labels(ds: Dataset, scenarios: list[str], k: int = 3, seed: int = 0,
                        thresholds: LabelThresholds | None = None) -> list[list[float]]:
    """Anchors for the detectable classes' kept labels, rounded for a readable config."""
    wh = label_sizes(ds, scenarios, ds.info.detectable_classes, thresholds)
    return [[round(float(w), 4), round(float(h), 4)] for w, h in kmeans_anchors(wh, k, seed)]
