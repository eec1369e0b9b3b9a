"""Detection metrics over views (numpy).

Two counting modes:

* ``strict`` (default): one-to-one, class-aware matching. Predictions are taken in descending
  score; each matches the unmatched ground truth of its class with the highest IoU if that IoU
  is >= the match threshold. TP = matches, FN = ground truths - TP, FP = the other predictions
  except those *ignored*: an unmatched prediction that covers a labelled road user of its class the
  label thresholds left out of the ground truth (too far, too truncated: ``ViewGroundTruth.
  excluded_boxes``), intersection over the prediction's area >= the threshold, is neither TP nor
  FP, as COCOeval treats crowd regions and KITTI its DontCare regions: finding a real road user is
  not a mistake, missing it is not counted either.
* ``paper``: the original code's counting, for comparison with the paper's tables. A prediction
  is a TP when its best IoU with *any* ground truth (any class) exceeds the threshold; several
  predictions may hit one object. FP = predictions - TP; FN = max(ground truths - TP, 0), so
  recall = min(TP, GT) / GT. (The clamp keeps recall <= 1; the original divided TP by GT.)
  Nothing is ignored (the original had no excluded objects).

COCO-style AP: all-point 101-sample interpolated precision, one-to-one class-aware matching
at IoU >= t, ignored predictions left out, averaged over classes with ground truth; AP50 and
AP50:95 (t = .50:.05:.95). It equals COCOeval's on the COCO export (whose ``iscrowd`` regions are
the excluded road users) when no image has more than COCOeval's 100 detections.

Recall by occlusion: every ground truth carries the target view's ``visible_fraction`` and
whether another source view sees it (visible_fraction > 0 there); recall is reported per bin.

Example::

    acc = MetricAccumulator(match_ious=[0.2, 0.4])
    acc.add(ViewDetections(...), ViewGroundTruth(...))
    summary = acc.summary()     # {"strict": {"0.4": {"precision", "recall", "f1", ...}}, ...}
"""
from __future__ import annotations

import numpy as np

from dataset_spec.boxes import box_iou
from pnyolo.evaluation.matching import (ViewDetections, ViewGroundTruth, as_boxes, best_iou, ignored_predictions,
                                        match_strict, precision_recall_ap, strict_pairs)
from pnyolo.evaluation.metrics_3d import metrics_3d
from pnyolo.evaluation.metrics_bins import binned_metrics

VISIBILITY_BINS = (("0%", 0.0, 0.0), ("0-40%", 0.0, 0.4), ("40-80%", 0.4, 0.8), ("80-100%", 0.8, 1.0))
HIDDEN_SEEN_ELSEWHERE = "hidden here, seen in another view"  # fully hidden in the target view, visible in another
COCO_IOUS = tuple(np.round(np.arange(0.5, 0.951, 0.05), 2))


def single_view_ceiling(visible_fractions) -> dict:
    """The recall no single-view detector can exceed: the share of ground-truth objects with any
    visible pixel in their own view (``visible_fraction > 0``). None without ground truth of measured
    visibility (none, or camera data)."""
    v = np.asarray(list(visible_fractions), dtype=np.float64).reshape(-1)
    v = v[~np.isnan(v)]  # not measured: no ceiling from it
    return {"recall_ceiling": float(np.mean(v > 0)) if v.size else None, "n": int(v.size),
            "fully_hidden": int(np.sum(v <= 0))}


# Hidden-but-seen objects by how many pixels of them the best other source view shows (renders' resolution).
OTHER_VIEW_PIXEL_BINS = ((1, 20), (20, 50), (50, 200), (200, None))


def other_pixels_group(pixels: int) -> str:
    """The recall group of a hidden-but-seen object by its visible pixels in the best other view."""
    lo, hi = next((lo, hi) for lo, hi in reversed(OTHER_VIEW_PIXEL_BINS) if pixels >= lo)
    return f"{HIDDEN_SEEN_ELSEWHERE}, {lo}-{hi} px in the best other view" if hi else \
        f"{HIDDEN_SEEN_ELSEWHERE}, {lo}+ px in the best other view"


def visibility_bin(v: float) -> str:
    if np.isnan(v):  # not measured (camera data without instance maps)
        return "unknown"
    if v <= 1e-6:
        return "0%"
    if v < 0.4:
        return "0-40%"
    if v < 0.8:
        return "40-80%"
    return "80-100%"


def match_paper(det: ViewDetections, gt: ViewGroundTruth, iou_threshold: float):
    """The original counting: a prediction is TP when its best IoU with any GT exceeds the threshold.

    Returns (det_tp (P,) bool, gt_hit (G,) bool: some TP prediction's best match is this GT).
    """
    P, G = len(det.boxes), len(gt.boxes)
    det_tp, gt_hit = np.zeros(P, dtype=bool), np.zeros(G, dtype=bool)
    if P == 0 or G == 0:
        return det_tp, gt_hit
    iou = box_iou(det.boxes, gt.boxes)
    best = iou.argmax(axis=1)
    det_tp = iou.max(axis=1) > iou_threshold
    gt_hit[best[det_tp]] = True
    return det_tp, gt_hit


def prf(tp: int, fp: int, fn: int) -> dict:
    p = tp / (tp + fp) if tp + fp else 0.0
    r = tp / (tp + fn) if tp + fn else 0.0
    f1 = 2 * p * r / (p + r) if p + r else 0.0
    return {"precision": p, "recall": r, "f1": f1, "tp": int(tp), "fp": int(fp), "fn": int(fn)}


def ap_inputs(records: list[tuple[ViewDetections, ViewGroundTruth]], iou_threshold: float,
              num_classes: int) -> list[list[tuple[np.ndarray, np.ndarray, int]]]:
    """Per record, per class: the (scores, TP flags) of its detections that are not ignored, and its ground-truth
    count: what AP is made of, matched once (``ap_from_inputs`` of any subset of records is that subset's AP)."""
    out = []
    for det, gt in records:
        row = []
        for c in range(num_classes):
            dm = np.asarray(det.classes) == c
            gm = np.asarray(gt.classes) == c
            d = ViewDetections(det.boxes[dm], det.scores[dm], det.classes[dm])
            g = ViewGroundTruth(gt.boxes[gm], gt.classes[gm])
            det_m, _ = match_strict(d, g, iou_threshold)
            keep = ~ignored_predictions(d, gt, det_m, iou_threshold)  # gt: every class, and the excluded boxes
            row.append((np.asarray(d.scores)[keep], det_m[keep], int(gm.sum())))
        out.append(row)
    return out


def ap_from_inputs(inputs: list[list[tuple[np.ndarray, np.ndarray, int]]], num_classes: int) -> float:
    """COCO 101-point AP from ``ap_inputs`` (records in order), mean over classes that have ground truth."""
    aps = []
    for c in range(num_classes):
        n_gt = sum(row[c][2] for row in inputs)
        if n_gt:
            scores = np.concatenate([row[c][0] for row in inputs]) if inputs else np.zeros(0)
            tps = np.concatenate([row[c][1] for row in inputs]) if inputs else np.zeros(0, bool)
            aps.append(precision_recall_ap(scores.tolist(), tps.tolist(), n_gt))
    return float(np.mean(aps)) if aps else 0.0


def average_precision(records: list[tuple[ViewDetections, ViewGroundTruth]], iou_threshold: float,
                      num_classes: int) -> float:
    """COCO 101-point AP at one IoU threshold, mean over classes that have ground truth."""
    return ap_from_inputs(ap_inputs(records, iou_threshold, num_classes), num_classes)


class MetricAccumulator:
    """Collects per-view detections and ground truth; ``summary()`` computes every metric."""

    def __init__(self, match_ious=(0.1, 0.2, 0.3, 0.4, 0.5, 0.6), num_classes: int = 2,
                 class_names: list[str] | None = None):
        self.match_ious = [float(t) for t in match_ious]
        self.num_classes = num_classes
        # names give the 3D metrics their per-class distances (pnyolo.evaluation.metrics_3d)
        self.class_names = list(class_names) if class_names is not None else [str(c) for c in range(num_classes)]
        self.info: dict = {}  # more figures for the summary (e.g. late fusion's bytes per car)
        self.records: list[tuple[ViewDetections, ViewGroundTruth]] = []
        self.units: list[str | None] = []  # each record's scenario: the bootstrap's resampled unit

    def add(self, det: ViewDetections, gt: ViewGroundTruth, unit: str | None = None) -> None:
        """One scored view; ``unit``: its scenario (the standard errors resample scenarios; None: not measured)."""
        self.records.append((det, gt))
        self.units.append(unit)

    def per_scenario(self) -> dict | None:
        """Per scenario (the records' units), what the F1 and hidden-but-seen recall at every match IoU are sums
        of: {scenario: {"counts": {iou: [TP, FP, FN]}, "hidden_seen": {iou: [found, n]}}}; None when a record has
        no scenario."""
        if not self.records or any(u is None for u in self.units):
            return None
        units = np.asarray(self.units)
        out: dict = {u: {"counts": {}, "hidden_seen": {}} for u in dict.fromkeys(self.units)}
        for t in self.match_ious:
            counts = self.per_view_counts(t)
            found = self._hidden_seen_per_view(t)
            for u in out:
                mask = units == u
                out[u]["counts"][f"{t:.1f}"] = [int(v) for v in counts[mask].sum(axis=0)]
                out[u]["hidden_seen"][f"{t:.1f}"] = [int(v) for v in found[mask].sum(axis=0)]
        return out

    def _hidden_seen_per_view(self, iou_threshold: float) -> np.ndarray:
        """(views, 2): hidden-but-seen road users found (strict) and their number, per record."""
        rows = []
        for det, gt in self.records:
            _, gt_m = match_strict(det, gt, iou_threshold)
            mask = (np.asarray(gt.visible_fraction) <= 1e-6) & np.asarray(gt.seen_elsewhere, dtype=bool)
            rows.append((int((gt_m & mask).sum()), int(mask.sum())))
        return np.asarray(rows, dtype=np.int64).reshape(-1, 2)

    def standard_errors(self, per_scenario: dict | None) -> dict:
        """Bootstrap standard errors over the layouts (``pnyolo.evaluation.bootstrap``) of F1 and hidden-but-seen
        recall at every match IoU and of AP50; None where there is one layout (or none measured)."""
        from pnyolo.evaluation.bootstrap import DRAWS, SEED, draws_of, f1_of, figure_se, hidden_recall_of, layout_groups

        row = {"per_scenario": per_scenario}
        groups = layout_groups(list(per_scenario)) if per_scenario is not None else []
        out = {"scenarios": None if per_scenario is None else len(per_scenario),
               "layouts": None if per_scenario is None else len(groups),
               "f1": {f"{t:.1f}": figure_se([row], f1_of(f"{t:.1f}")) for t in self.match_ious},
               "hidden_seen_recall": {f"{t:.1f}": figure_se([row], hidden_recall_of(f"{t:.1f}"))
                                      for t in self.match_ious}, "ap50": None}
        if len(groups) > 1:  # AP50 over drawn layouts (every view of a drawn layout's scenarios)
            inputs, order = ap_inputs(self.records, 0.5, self.num_classes), list(per_scenario)
            by_unit = [[inputs[k] for k, u in enumerate(self.units) if order.index(u) in g] for g in groups]
            idx = draws_of(len(groups), DRAWS // 5, SEED)
            aps = [ap_from_inputs([r for j in draw for r in by_unit[j]], self.num_classes) for draw in idx]
            out["ap50"] = float(np.std(aps, ddof=1))
        return out

    def per_view_counts(self, iou_threshold: float) -> np.ndarray:
        """(views, 3) int array: strict TP, FP, FN of each added view, in the order added (ignored
        predictions in none of them)."""
        rows = []
        for det, gt in self.records:
            det_m, gt_m = match_strict(det, gt, iou_threshold)
            fp = ~det_m & ~ignored_predictions(det, gt, det_m, iou_threshold)
            rows.append((int(det_m.sum()), int(fp.sum()), int((~gt_m).sum())))
        return np.asarray(rows, dtype=np.int64).reshape(-1, 3)

    def counts(self, iou_threshold: float, mode: str = "strict") -> dict:
        if mode == "strict":
            tp, fp, fn = (int(v) for v in self.per_view_counts(iou_threshold).sum(axis=0))
        elif mode == "paper":
            tp = fp = fn = 0
            for det, gt in self.records:
                det_tp, _ = match_paper(det, gt, iou_threshold)
                t = int(det_tp.sum())
                tp += t
                fp += len(det.boxes) - t
                fn += max(len(gt.boxes) - t, 0)
        else:
            raise ValueError(f"unknown metric mode {mode!r} (strict | paper)")
        out = prf(tp, fp, fn)
        if mode == "paper":  # recall = min(TP, GT) / GT (see module docstring)
            n_gt = sum(len(gt.boxes) for _, gt in self.records)
            out["recall"] = min(tp, n_gt) / n_gt if n_gt else 0.0
            p, r = out["precision"], out["recall"]
            out["f1"] = 2 * p * r / (p + r) if p + r else 0.0
        return out

    def recall_breakdown(self, iou_threshold: float) -> dict:
        """Strict recall per visible-fraction bin of the target view and per seen-elsewhere flag."""
        hits: dict[str, list[int]] = {}
        for det, gt in self.records:
            _, gt_m = match_strict(det, gt, iou_threshold)
            for k in range(len(gt.boxes)):
                keys = [f"visible {visibility_bin(float(gt.visible_fraction[k]))}",
                        "seen in another view" if gt.seen_elsewhere[k] else "not seen in another view"]
                if gt.visible_fraction[k] <= 1e-6 and gt.seen_elsewhere[k]:
                    keys.append(HIDDEN_SEEN_ELSEWHERE)
                    if gt.other_view_pixels is not None:
                        keys.append(other_pixels_group(int(gt.other_view_pixels[k])))
                for key in keys:
                    h = hits.setdefault(key, [0, 0])
                    h[0] += int(gt_m[k])
                    h[1] += 1
        order = [f"visible {b[0]}" for b in VISIBILITY_BINS] + ["seen in another view", "not seen in another view",
                                                                 HIDDEN_SEEN_ELSEWHERE]
        order += [other_pixels_group(lo) for lo, _ in OTHER_VIEW_PIXEL_BINS]
        return {k: {"recall": hits[k][0] / hits[k][1], "n": hits[k][1]} for k in order if k in hits}

    def false_positive_breakdown(self, iou_threshold: float) -> dict:
        """Where the false positives (strict matching) lie, each counted once, first match wins:

        * ``on a ground-truth object``: IoU >= ``iou_threshold`` with some ground-truth box of any
          class (a duplicate, a wrong class, or a box the one-to-one matching gave to another);
        * ``near an object``: some overlap (IoU > 0) with a ground-truth or excluded box, a poorly
          placed box;
        * ``on no labelled object``: no overlap at all (e.g. a multi-view "ghost" where a ray
          crosses another view's object off its true depth).

        ``ignored``: predictions on an excluded road user (not false positives, see the module
        docstring), counted beside them.
        """
        names = ("on a ground-truth object", "near an object", "on no labelled object")
        counts = dict.fromkeys(names, 0)
        ignored = 0
        for det, gt in self.records:
            det_m, _ = match_strict(det, gt, iou_threshold)
            skip = ignored_predictions(det, gt, det_m, iou_threshold)
            ignored += int(skip.sum())
            fp = as_boxes(det.boxes)[~det_m & ~skip]
            if len(fp) == 0:
                continue
            best_gt = best_iou(fp, as_boxes(gt.boxes))
            best_any = np.maximum(best_gt, best_iou(fp, as_boxes(gt.excluded_boxes)))
            on_gt = best_gt >= iou_threshold
            near = ~on_gt & (best_any > 0)
            for name, mask in zip(names, (on_gt, near, ~on_gt & ~near)):
                counts[name] += int(mask.sum())
        total = sum(counts.values())
        return {"n": total, **{k: {"count": v, "share": v / total if total else 0.0} for k, v in counts.items()},
                "ignored": ignored}

    def distance_error(self, iou_threshold: float = 0.4) -> dict:
        """Mean absolute distance error of strictly matched detections that carry a distance (metres)."""
        errs = []
        for det, gt in self.records:
            if det.distances is None or gt.distances is None or len(det.boxes) == 0 or len(gt.boxes) == 0:
                continue
            pairs = strict_pairs(det, gt, iou_threshold)
            for p in np.where((pairs >= 0) & np.isfinite(np.asarray(det.distances, dtype=np.float64)))[0]:
                errs.append(abs(float(det.distances[p]) - float(gt.distances[pairs[p]])))
        return {"mean_abs_m": float(np.mean(errs)) if errs else None, "n": len(errs)}

    def summary(self) -> dict:
        out = {"views": len(self.records), "ground_truth": int(sum(len(g.boxes) for _, g in self.records)),
               "predictions": int(sum(len(d.boxes) for d, _ in self.records)), **self.info}
        for mode in ("strict", "paper"):
            out[mode] = {f"{t:.1f}": self.counts(t, mode) for t in self.match_ious}
        out["ap50"] = average_precision(self.records, 0.5, self.num_classes)
        out["ap50_95"] = float(np.mean([average_precision(self.records, t, self.num_classes) for t in COCO_IOUS]))
        out["recall_by_visibility"] = {f"{t:.1f}": self.recall_breakdown(t) for t in self.match_ious}
        out["distance_error"] = self.distance_error()
        out["false_positives"] = {f"{t:.1f}": self.false_positive_breakdown(t) for t in self.match_ious}
        out["3d"] = metrics_3d(self.records, self.class_names)
        out["by_bin"] = binned_metrics(self.records, 0.2 if 0.2 in self.match_ious else self.match_ious[0],
                                       self.num_classes)
        out["single_view_ceiling"] = single_view_ceiling(
            np.concatenate([np.asarray(g.visible_fraction, dtype=np.float64).reshape(-1) for _, g in self.records])
            if self.records else [])
        out["per_scenario"] = self.per_scenario()
        out["standard_errors"] = self.standard_errors(out["per_scenario"])
        return out
