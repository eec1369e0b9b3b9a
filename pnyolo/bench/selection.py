"""Choosing each model's operating point on validation, the same procedure for every model (the test
split is scored by ``pnyolo.bench.testing``).

    rows = threshold_sweep(preds, cfg.eval, preset.conf_grid)              # P/R/F1 and hidden recall per threshold
    pick = select_threshold(rows)                                          # the one-standard-error rule
    chosen = choose_on_validation(preset, data, runs, kind, class_names)   # its Trained, Choice and predictions
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dataset_spec.cli_support import UserError
from dataset_spec.splits import layout_of
from pnyolo.bench.plan import PredictionPlan, predict_plan
from pnyolo.bench.presets import BenchPreset
from pnyolo.bench.record import Choice, HiddenPoint
from pnyolo.bench.stages import log
from pnyolo.config.checks import EVAL_STATS
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.engine.checkpoint import load_detector, read_checkpoint
from pnyolo.engine.predict import Trained
from pnyolo.engine.runtime import pick_device
from pnyolo.evaluation.bootstrap import draws_of, spread_text
from pnyolo.evaluation.evaluate import scored_views
from pnyolo.evaluation.metrics import HIDDEN_SEEN_ELSEWHERE as HIDDEN_SEEN
from pnyolo.evaluation.metrics import MetricAccumulator, prf
from pnyolo.models import eval_stats, use_eval_stats


@dataclass
class Chosen:
    """A model at the operating point chosen on validation: the ``trained`` model set to it, the ``choice``, and
    its clean ``val`` predictions (at the most depth peaks tried: decoding takes the chosen number)."""

    trained: Trained
    choice: Choice
    val: object  # pnyolo.engine.predict.Predictions


def choose_on_validation(preset: BenchPreset, data: Path, runs: Path, kind: str, class_names: list[str],
                         vals: dict | None = None, paths: dict | None = None, device=None) -> Chosen:
    """One model's operating point, the same procedure for every model: of the run's end (latest.pt)
    and its best-validation checkpoint (best.pt, picked during training by F1@0.4 at a fixed
    threshold), each with batch norm's running or the item's own statistics (EVAL_STATS; one pass for a
    model without an encoder), and each candidate of the decoding settings its kind tunes
    (``Model.tuned``: the preset's depth peaks, NMS IoUs and depth gaps): the one with the best F1 (at
    ``select_iou``) at its own tuned threshold. Each (checkpoint, statistics) predicts the validation split
    once, at the most depth peaks tried; every setting decodes those outputs. ``vals`` keeps the validation
    items of each grid (data.image_scale, data.cell_px) for the next model; ``paths``: the model's own
    configured paths (its feature cache), which a stored checkpoint never sets; ``device``: where the models
    run (None: the machine's best, ``pick_device("auto")``)."""
    device = pick_device("auto") if device is None else device
    vals = {} if vals is None else vals
    best = None
    for name in ("latest.pt", "best.pt"):
        path = runs / kind / name
        if not path.is_file():
            continue
        ckpt = read_checkpoint(path)
        m, c = load_detector(ckpt, path, class_names, device, paths=paths)
        key = (c.data.image_scale, c.data.cell_px)
        if key not in vals:
            vals[key] = MultiViewDataset(data, "val", c, training=False, every_camera=preset.every_camera)
        step = ckpt.get("train_state", {}).get("step")
        stats_options = EVAL_STATS if m.encoder is not None else (eval_stats(c),)
        peaks_options = preset.depth_peaks if "depth_peaks" in m.tuned else (1,)
        for stats in stats_options:
            use_eval_stats(m, c, stats)
            plan = PredictionPlan((kind,), peaks=max(peaks_options))
            preds = predict_plan(plan, {kind: Trained(path, m, c)}, vals[key], device).models[kind].clean
            for peaks, (nms, gap) in itertools.product(peaks_options, _nms_options(preset, m)):
                ev = replace(c.eval, depth_peaks=peaks, nms_iou=nms or c.eval.nms_iou, depth_gap=gap)  # a candidate
                rows = threshold_sweep(preds, ev, preset.conf_grid, preset.iou)
                pick = select_threshold(rows, seed=0)
                log(f"{kind} {name} (step {step}, {stats} statistics, {peaks} depth peak(s), NMS IoU {nms or 'none'}"
                    f"{'' if gap is None else f', depth gap {gap:g} m'}): validation F1@{preset.iou} "
                    f"{pick['best_val_f1']:.3f} at confidence {pick['best_threshold']:.2f} (standard error "
                    f"{spread_text(pick['val_f1_se'], pick['val_layouts'])}); one-SE choice "
                    f"{pick['threshold']:.2f} (F1 {pick['val_f1']:.3f})")
                if best is None or pick["best_val_f1"] > best[0].best_val_f1:
                    best = (Choice(name, step, stats, peaks, nms, gap, val_sweep=_without_layout_counts(rows),
                                   **pick), path, m, c, preds)
    if best is None:
        raise UserError(f"{runs / kind} holds no checkpoint to evaluate")
    choice, path, m, c, preds = best
    use_eval_stats(m, c, choice.eval_stats)
    point = replace(c.eval, conf_threshold=choice.threshold, depth_gap=choice.depth_gap,
                    nms_iou=choice.nms_iou or c.eval.nms_iou, depth_peaks=choice.depth_peaks)
    return Chosen(Trained(path, m, replace(c, eval=point)), choice, preds)  # the chosen point, a value of its own


def _nms_options(preset: BenchPreset, model) -> list[tuple[float | None, float | None]]:
    """(NMS IoU, depth gap) pairs to try: each of the preset's NMS IoUs for a kind decoded by 2D NMS, each
    with its depth gaps for a kind that tunes depth-gated NMS; (None, None) alone for a kind that tunes
    neither (a ground-plane model's detections are merged in the world, not by 2D NMS)."""
    if "nms_iou" not in model.tuned:
        return [(None, None)]
    return list(itertools.product(preset.nms_grid, preset.depth_gaps if "depth_gap" in model.tuned else (None,)))


def threshold_sweep(preds, ev, grid: tuple[float, ...], iou: str = "0.2") -> list[dict]:
    """Precision, recall, F1@``iou`` and hidden-but-seen-elsewhere recall at each confidence threshold of
    ``grid`` (NMS at ``ev.nms_iou`` and ``ev.depth_gap``) of a model's predictions, plus ``layout_counts``:
    strict (TP, FP, FN) per layout, summed over its scenarios (a scene and its redraws) and their lighting variants
    (the units of the bootstrap in ``select_threshold``). Each item is decoded once, at the lowest threshold; higher ones keep the
    detections above them."""
    lowest = min(grid)
    decoded = [(p.item, preds.detections_at(k, ev, lowest)) for k, p in enumerate(preds.items)]
    return sweep_views(decoded, grid, iou, len(decoded[0][0].class_names) if decoded else 0)


def sweep_views(decoded: list[tuple], grid: tuple[float, ...], iou: str, num_classes: int) -> list[dict]:
    """``threshold_sweep``'s rows from (item, its detections per view at the grid's lowest threshold)."""
    layout_index = {s: k for k, s in enumerate(dict.fromkeys(layout_of(item.scenario) for item, _ in decoded))}
    view_layout = np.repeat([layout_index[layout_of(item.scenario)] for item, _ in decoded],
                            [len(item.scored) for item, _ in decoded])
    views = [(det, gt) for item, dets in decoded for _, det, gt in scored_views(item, dets)]
    rows = []
    for t in grid:
        acc = MetricAccumulator([float(iou)], num_classes)
        for det, gt in views:
            acc.add(det.above(t), gt)
        per_view = acc.per_view_counts(float(iou))  # matched once; totals and per-scenario sums from it
        per_layout = np.zeros((len(layout_index), 3), np.int64)
        np.add.at(per_layout, view_layout, per_view)
        hs = acc.recall_breakdown(float(iou)).get(HIDDEN_SEEN)
        totals = prf(*(int(v) for v in per_view.sum(axis=0)))
        rows.append({"threshold": t, **{k: totals[k] for k in ("precision", "recall", "f1")},
                     "hidden_seen_recall": hs["recall"] if hs else None, "layout_counts": per_layout.tolist()})
    return rows


def _f1(counts: np.ndarray) -> np.ndarray:
    """F1 = 2 TP / (2 TP + FP + FN) over the last axis (TP, FP, FN); 0 where undefined."""
    tp, fp, fn = (counts[..., i].astype(np.float64) for i in range(3))
    den = 2 * tp + fp + fn
    return np.where(den > 0, 2 * tp / np.maximum(den, 1), 0.0)


def select_threshold(rows: list[dict], draws: int = 1000, seed: int = 0) -> dict:
    """The confidence threshold to use, from a validation ``threshold_sweep``: the one-standard-error
    rule. The best threshold's F1 has a standard error, estimated by resampling the validation
    layouts with replacement (``draws`` times, seeded); of the thresholds whose F1 is within one
    standard error of the best, the lowest (the most recall) is chosen. With a handful of validation
    scenes, F1 differences smaller than that are noise, and a detector of hidden road users should not
    give up recall for them. The resampled unit is the layout, not the item: a scenario's lighting
    variants show the same road users from the same cameras, and its redraws the same streets, so resampling
    them as if independent would understate the noise. One layout (no spread): the best threshold (ties: the
    lower one)."""
    order = sorted(range(len(rows)), key=lambda i: rows[i]["threshold"])
    f1 = np.array([rows[i]["f1"] for i in order])
    best = int(np.argmax(f1))
    counts = np.asarray(rows[order[best]]["layout_counts"], dtype=np.int64).reshape(-1, 3)
    se = 0.0
    if len(counts) > 1:
        se = float(_f1(counts[draws_of(len(counts), draws, seed)].sum(axis=1)).std(ddof=1))
    chosen = next(j for j in range(len(order)) if f1[j] >= f1[best] - se)
    return {"threshold": rows[order[chosen]]["threshold"], "val_f1": float(f1[chosen]),
            "best_threshold": rows[order[best]]["threshold"], "best_val_f1": float(f1[best]), "val_f1_se": se,
            "rule": "one-standard-error", "val_layouts": len(counts)}


def hidden_target_point(val_rows: list[dict], test_rows: list[dict], target: float) -> HiddenPoint:
    """The operating point a user who needs ``target`` recall on hidden-but-seen objects would take,
    chosen on validation like the F1 point: the highest confidence threshold whose validation
    hidden-but-seen recall reaches ``target`` (the most precise one that does), with the test split's
    figures there (same checkpoint and NMS; the sweeps share one threshold grid)."""
    val = {r["threshold"]: r for r in val_rows}
    test = {r["threshold"]: r for r in test_rows}
    reached = [t for t, r in val.items() if r["hidden_seen_recall"] is not None and r["hidden_seen_recall"] >= target]
    recalls = [r["hidden_seen_recall"] for r in val.values() if r["hidden_seen_recall"] is not None]
    best = max(recalls) if recalls else None
    if not reached:
        return HiddenPoint(target, None, best)
    t = max(reached)
    return HiddenPoint(target, t, best, val_f1=val[t]["f1"], val_hidden_recall=val[t]["hidden_seen_recall"],
                       test_f1=test[t]["f1"], test_hidden_recall=test[t]["hidden_seen_recall"])


def _without_layout_counts(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k != "layout_counts"} for r in rows]


