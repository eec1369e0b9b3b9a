"""Figures by distance and by box height: where each model fails, set beside the paper's range.

    bins = binned_metrics(acc.records, f1_iou=0.2, num_classes=2)
    bins["distance"]["0-13 m"]   # {"f1", "precision", "recall", "ap50", "hidden_seen_recall", "n", "n_hidden_seen"}
    bins["height"]["< 12 px"]

Matching is the strict one-to-one matching over the whole view (``pnyolo.evaluation.metrics``), so
a bin's TP and FN are those of the full figures restricted to its ground truth. A detection matched
to a road user outside the bin counts in neither direction there; an unmatched one (and not ignored
on an excluded road user) is a false positive of the bin its own estimate falls in, as COCO's area
ranges treat unmatched detections: its box height, or its distance estimate for the distance bins.
A model without distance estimates (the single view) has recall but no precision, F1 or AP by
distance (None). Box heights are in the evaluated images' pixels.
"""
from __future__ import annotations

import math

import numpy as np

from pnyolo.evaluation.matching import ignored_predictions, precision_recall_ap, strict_pairs

DISTANCE_BINS = (("0-13 m", 0.0, 13.0), ("13-25 m", 13.0, 25.0), ("25-40 m", 25.0, 40.0))  # 0-13 m: the paper's range
HEIGHT_BINS = (("< 12 px", 0.0, 12.0), ("12-24 px", 12.0, 24.0), (">= 24 px", 24.0, math.inf))


def _heights(boxes) -> np.ndarray:
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    return b[:, 3] - b[:, 1]


def _attributes(det, gt, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """(detections' (P,), ground truth's (G,)) value of the binned quantity (NaN: no estimate)."""
    if kind == "height":
        return _heights(det.boxes), _heights(gt.boxes)
    d = np.full(len(det.boxes), np.nan) if det.distances is None else np.asarray(det.distances, dtype=np.float64)
    g = np.full(len(gt.boxes), np.nan) if gt.distances is None else np.asarray(gt.distances, dtype=np.float64)
    return d, g


def _bin_figures(views: list[dict], lo: float, hi: float, num_classes: int) -> dict:
    tp = fp = fn = n_hs = hit_hs = 0
    unknown = False
    ap_scores = {c: [] for c in range(num_classes)}
    ap_tps = {c: [] for c in range(num_classes)}
    ap_gt = dict.fromkeys(range(num_classes), 0)
    for v in views:
        g_in = (v["g_attr"] >= lo) & (v["g_attr"] < hi)
        d_in = (v["d_attr"] >= lo) & (v["d_attr"] < hi)
        for key, pairs, ignored in (("f1", v["pairs"], v["ignored"]), ("ap", v["pairs50"], v["ignored50"])):
            matched = pairs >= 0
            tp_in = matched & g_in[np.where(matched, pairs, 0)] if len(g_in) else np.zeros_like(matched)
            free = ~matched & ~ignored
            unknown |= bool(np.any(free & np.isnan(v["d_attr"])))
            fp_in = free & d_in
            if key == "f1":
                gt_hit = np.zeros(len(g_in), dtype=bool)
                gt_hit[pairs[matched]] = True
                tp += int(tp_in.sum())
                fp += int(fp_in.sum())
                fn += int((g_in & ~gt_hit).sum())
                hs = g_in & v["hidden_seen"]
                n_hs += int(hs.sum())
                hit_hs += int((hs & gt_hit).sum())
            else:
                for c in range(num_classes):
                    keep = (v["classes"] == c) & (tp_in | fp_in)
                    ap_scores[c] += v["scores"][keep].tolist()
                    ap_tps[c] += tp_in[keep].tolist()
                    ap_gt[c] += int((g_in & (v["gt_classes"] == c)).sum())
    p = tp / (tp + fp) if tp + fp else 0.0
    r = tp / (tp + fn) if tp + fn else 0.0
    aps = [precision_recall_ap(ap_scores[c], ap_tps[c], ap_gt[c]) for c in range(num_classes) if ap_gt[c]]
    out = {"recall": r if tp + fn else None, "n": tp + fn, "hidden_seen_recall": hit_hs / n_hs if n_hs else None,
           "n_hidden_seen": n_hs, "precision": p, "f1": 2 * p * r / (p + r) if p + r else 0.0,
           "ap50": float(np.mean(aps)) if aps else None}
    if unknown:  # some false positives cannot be placed in a bin: no precision, F1 or AP here
        out.update(precision=None, f1=None, ap50=None)
    return out


def binned_metrics(records: list, f1_iou: float, num_classes: int) -> dict:
    """F1, precision and recall at ``f1_iou``, AP50 and hidden-but-seen recall per distance bin and per
    box-height bin (see the module docstring)."""
    matched = []  # each view matched once; the bin kinds differ only in the quantity binned
    for det, gt in records:
        pairs, pairs50 = strict_pairs(det, gt, f1_iou), strict_pairs(det, gt, 0.5)
        matched.append({"pairs": pairs, "pairs50": pairs50,
                        "ignored": ignored_predictions(det, gt, pairs >= 0, f1_iou),
                        "ignored50": ignored_predictions(det, gt, pairs50 >= 0, 0.5),
                        "classes": np.asarray(det.classes), "scores": np.asarray(det.scores, dtype=np.float64),
                        "gt_classes": np.asarray(gt.classes),
                        "hidden_seen": (np.asarray(gt.visible_fraction) <= 1e-6) & np.asarray(gt.seen_elsewhere)})
    out = {}
    for kind, bins in (("distance", DISTANCE_BINS), ("height", HEIGHT_BINS)):
        views = [{**m, **dict(zip(("d_attr", "g_attr"), _attributes(det, gt, kind)))}
                 for m, (det, gt) in zip(matched, records)]
        out[kind] = {name: _bin_figures(views, lo, hi, num_classes) for name, lo, hi in bins}
    return out
