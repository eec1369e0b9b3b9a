"""The benchmark report: ``report.md`` with pictures and ``report.json`` with every figure.

    result = write_report(run)     # run: the BenchRun every stage filled in (pnyolo.bench.record)
    result["targets"]      # {target text: True / False / None (nothing to measure)}
    result["target_figures"]   # {target text: what was measured}
"""
from __future__ import annotations

import textwrap
from dataclasses import asdict
from pathlib import Path

from dataset_spec.atomic import atomic_savefig, atomic_write_json, atomic_write_text
from pnyolo.bench.presets import BEV, MULTI, SINGLE, BenchPreset, multi_view_kinds
from pnyolo.bench.record import BenchRun
from pnyolo.bench.robustness import read_sweep, robustness_lines, trained_with_noise
from pnyolo.bench.selection import hidden_target_point
from pnyolo.bench.stages import label_thresholds
from pnyolo.evaluation.coverage import coverage_markdown
from pnyolo.evaluation.evaluate import FUSION, late_fusion_name, own_view_name
from pnyolo.evaluation.message import DETECTION_BYTES, HEADER_BYTES
from pnyolo.evaluation.metrics import HIDDEN_SEEN_ELSEWHERE as HIDDEN_SEEN
from pnyolo.evaluation.metrics import OTHER_VIEW_PIXEL_BINS, other_pixels_group
from pnyolo.evaluation.report import comparison_markdown, false_positive_markdown, write_comparison
from pnyolo.models import MODEL_REGISTRY, model_class



def _hidden_target_lines(point: dict, single_f1: float, iou: str) -> list[str]:
    head = (f"**Operating point for the hidden-recall target** (for information; the targets below are judged at "
            f"the F1 point): the highest confidence whose validation recall@{iou} on hidden-but-seen objects "
            f"reaches {point['target']:g}, same checkpoint and NMS. ")
    if point["threshold"] is None:
        return [head + f"No candidate threshold reaches it on validation (at most {_fmt(point['best_val_recall'])}).", ""]
    return [head + f"Confidence {point['threshold']:.2f} (validation F1@{iou} {point['val_f1']:.3f}, hidden-but-seen "
            f"recall {point['val_hidden_recall']:.3f}); on test F1@{iou} {point['test_f1']:.3f} (single view at its own "
            f"point {single_f1:.3f}) and hidden-but-seen recall {_fmt(point['test_hidden_recall'])}.", ""]


def _fmt(v: float | None) -> str:
    """A share to three decimals, or n/a where there was nothing to measure."""
    return "n/a" if v is None else f"{v:.3f}"


def _recall(summary: dict, iou: str, group: str) -> tuple[float | None, int]:
    g = summary["recall_by_visibility"].get(iou, {}).get(group)
    return (g["recall"], g["n"]) if g else (None, 0)


def recall_plot(summaries: dict[str, dict], path: Path, iou: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    groups = [g for g in next(iter(summaries.values()))["recall_by_visibility"].get(iou, {})
              if not g.startswith(HIDDEN_SEEN + ",")]  # the split by the other view's pixels: in the table
    fig, ax = plt.subplots(figsize=(7, 3.6))
    width = 0.8 / max(1, len(summaries))
    for k, (name, s) in enumerate(summaries.items()):
        vals = [(_recall(s, iou, g)[0] or 0.0) for g in groups]
        ax.bar(np.arange(len(groups)) + k * width, vals, width, label=name)
    ax.set_xticks(np.arange(len(groups)) + width * (len(summaries) - 1) / 2)
    ax.set_xticklabels([textwrap.fill(g, 12) for g in groups], fontsize=7)
    ax.set_ylabel(f"recall @ IoU {iou}")
    ax.set_ylim(0, 1)
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)


def _seconds(v) -> str:
    if isinstance(v, dict):  # a reused stage: what it took when it ran
        return "reused" + (f" (took {v['trained_seconds']:.0f} when run)" if v.get("trained_seconds") else "")
    return "reused" if v is None else f"{v:.0f}"


def _one_per_scenario_first(pictures: list[Path], scenarios: list[str]) -> list[Path]:
    """``pictures`` (named ``SCENARIO_...``) reordered round-robin over ``scenarios``, so the first few
    shown come from different streets rather than one street under every lighting."""
    def scenario_of(p: Path) -> str:
        return max((s for s in scenarios if p.name.startswith(s + "_")), key=len, default="")

    rank: dict[str, int] = {}
    keyed = []
    for p in pictures:
        s = scenario_of(p)
        keyed.append((rank.setdefault(s, 0), p.name, p))
        rank[s] += 1
    return [p for _, _, p in sorted(keyed)]


def _selection_text(kind: str, summary: dict, iou: str) -> str:
    sel = summary["selection"]
    stats = f", {sel['eval_stats']} batch-norm statistics" if "eval_stats" in sel else ""
    stats += f", NMS IoU {sel['nms_iou']}" if sel.get("nms_iou") is not None else ""
    stats += f", depth gap {sel['depth_gap']:g} m" if sel.get("depth_gap") is not None else ""
    stats += f", {sel['depth_peaks']} depth peaks" if sel.get("depth_peaks", 1) > 1 else ""
    text = f"{kind} `{sel['checkpoint']}` (step {sel['step']}{stats}) at {summary['conf_threshold']:.2f}"
    if "best_threshold" in sel:
        text += (f" (validation F1@{iou} {sel['val_f1']:.3f}; best {sel['best_val_f1']:.3f} at "
                 f"{sel['best_threshold']:.2f}, standard error {sel['val_f1_se']:.3f})")
    return text


def _sweep_table(grid: tuple[float, ...], sweeps: dict[str, list[dict]]) -> str:
    """Markdown: one row per confidence threshold, one column per sweep, cells ``F1 / hidden recall``."""
    lines = ["| confidence | " + " | ".join(sweeps) + " |", "|---|" + "---|" * len(sweeps)]
    for i, t in enumerate(grid):  # every sweep ran over the same grid, in its order
        cells = []
        for rows in sweeps.values():
            hs = rows[i]["hidden_seen_recall"]
            cells.append(f"{rows[i]['f1']:.3f} / {_fmt(hs)}")
        lines.append(f"| {t:.2f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


# Targets: the world-space pixelNeRF-YOLO's (what the other cameras must add, its sampling) and the
# best multi-view model's (the ground-plane issue), judged at each model's validation-chosen point.
OWN_VIEW_MARGIN = 0.2  # hidden-but-seen recall at least this much above the own-view-only ablation
COVERAGE_TARGETS = {"on_pixels": 0.5, "near_pixels": 0.9, "in_box": 0.9}  # hidden-but-seen, every class
BEV_COVERAGE_TARGETS = {"near_pixels": 0.9, "in_box": 0.9}
BEST_HIDDEN_RECALL, BEST_F1 = 0.6, 0.55
RECALL_1M = 0.5  # hidden-but-seen recall within 1 m on the ground plane, models with 3D outputs
INFERENCE_FACTOR = 2.0  # a multi-view model's time per frame at most this times the single view's


def best_multi_view(summaries: dict) -> str | None:
    """The multi-view model with the best validation F1 (where models are compared, never test)."""
    cands = [k for k in multi_view_kinds(summaries) if "selection" in summaries[k]]
    return max(cands, key=lambda k: summaries[k]["selection"]["best_val_f1"]) if cands else None


def bench_targets(preset: BenchPreset, summaries: dict, timings: dict, iou: str) -> dict[str, tuple[bool | None, str]]:
    """{target: (PASS / FAIL / None when nothing was measured, the figures it was judged on)}."""
    out: dict[str, tuple[bool | None, str]] = {}

    def at_least(name: str, value: float | None, target: float, text: str | None = None) -> None:
        out[name] = (None if value is None else value >= target, text or f"{_fmt(value)} (target {target:g})")

    f1 = {k: s["strict"][iou]["f1"] for k, s in summaries.items()}
    if MULTI in summaries:
        hs, n = _recall(summaries[MULTI], iou, HIDDEN_SEEN)
        at_least(f"{MULTI} recall on objects hidden in the target view but seen in another (IoU {iou}) >= "
                 f"{preset.hidden_recall_target:g}", hs, preset.hidden_recall_target, f"{_fmt(hs)} (n = {n})")
        if SINGLE in summaries:
            out[f"{MULTI} F1@{iou} > single-view F1@{iou}"] = (f1[MULTI] > f1[SINGLE],
                                                               f"{f1[MULTI]:.3f} against {f1[SINGLE]:.3f}")
    for kind in multi_view_kinds(summaries):
        own = summaries.get(own_view_name(kind))
        if kind in summaries and own is not None:
            full_hs, own_hs = (_recall(s, iou, HIDDEN_SEEN)[0] for s in (summaries[kind], own))
            gain = None if full_hs is None or own_hs is None else full_hs - own_hs
            at_least(f"{kind} hidden-but-seen recall >= own view only + {OWN_VIEW_MARGIN:g}", gain, OWN_VIEW_MARGIN,
                     f"{_fmt(full_hs)} against {_fmt(own_hs)} (+{_fmt(gain)}; target +{OWN_VIEW_MARGIN:g})")
        for cls, groups in summaries.get(kind, {}).get("coverage", {}).items():
            rec = groups["hidden-but-seen"]
            for m, target in (COVERAGE_TARGETS if kind == MULTI else BEV_COVERAGE_TARGETS).items():
                at_least(f"{kind} coverage of hidden-but-seen {cls}s: {m.replace('_', ' ')} >= {target:g}", rec[m],
                         target, f"{_fmt(rec[m])} of {rec['n']} (target {target:g})")
    best = best_multi_view(summaries)
    if best is not None:
        s = summaries[best]
        hs, n = _recall(s, iou, HIDDEN_SEEN)
        at_least(f"best multi-view model ({best}, by validation F1): hidden-but-seen recall@{iou} >= "
                 f"{BEST_HIDDEN_RECALL:g}", hs, BEST_HIDDEN_RECALL, f"{_fmt(hs)} (n = {n})")
        bins = [_recall(s, iou, other_pixels_group(lo))[0] for lo, _ in OTHER_VIEW_PIXEL_BINS]
        rising = None if bins[0] is None or bins[-1] is None else bins[-1] > bins[0]
        out[f"best multi-view model ({best}): hidden-but-seen recall rises with the object's pixels in the best "
            "other view (200+ px above 1-20 px)"] = (rising, " / ".join(_fmt(b) for b in bins) + " over the bins "
                                                             + ", ".join(f"{lo}-{hi or ''}" for lo, hi in OTHER_VIEW_PIXEL_BINS))
        at_least(f"best multi-view model ({best}): F1@{iou} >= {BEST_F1:g}", f1[best], BEST_F1)
    for name, s in summaries.items():
        m3 = s.get("3d")
        if m3 and name in (MULTI, BEV, late_fusion_name(BEV)):
            r = m3["recall_within_1m"]["hidden here, seen in another view"]
            at_least(f"{name}: hidden-but-seen recall within 1 m on the ground plane >= {RECALL_1M:g}", r["recall"],
                     RECALL_1M, f"{_fmt(r['recall'])} (n = {r['n']})")
    if SINGLE in summaries and summaries[SINGLE].get("inference_ms"):
        single = summaries[SINGLE]["inference_ms"]
        for kind in multi_view_kinds(summaries):
            if summaries.get(kind, {}).get("inference_ms"):
                ms = summaries[kind]["inference_ms"]
                out[f"{kind} inference per frame <= {INFERENCE_FACTOR:g} x single view"] = (
                    ms <= INFERENCE_FACTOR * single, f"{ms:.0f} ms against {single:.0f} ms")
    if preset.time_budget_s is not None:
        spent = _cached_time(timings)
        out[f"the preset within {preset.time_budget_s / 60:g} minutes with the dataset cached"] = (
            None if spent is None else spent <= preset.time_budget_s,
            "n/a (a reused stage has no recorded time)" if spent is None else f"{spent / 60:.0f} min")
    return out


def _cached_time(timings: dict) -> float | None:
    """Seconds of everything but rendering, as a run with the dataset cached spends: a reused training
    counts the seconds it took when it ran (None: one with no record of them)."""
    rest = [v.get("trained_seconds") if isinstance(v, dict) else v for k, v in timings.items()
            if k not in ("total", "render (blender-gen)")]
    if any(not isinstance(v, (int, float)) for v in rest):
        return None
    return float(sum(rest))


def _own_view_lines(summaries: dict, iou: str) -> list[str]:
    """The report's paragraph on each multi-view model with each view's own image alone (if evaluated)."""
    lines = []
    for kind in multi_view_kinds(summaries):
        own = summaries.get(own_view_name(kind))
        if own is None or kind not in summaries:
            continue
        full_hs, own_hs = (_recall(s, iou, HIDDEN_SEEN)[0] for s in (summaries[kind], own))
        how = ("each view's rays sampling only that view's image features (the views are still encoded together)"
               if kind == MULTI else "each view's grid pooling only that view's features, detections projected "
               "into that view only")
        lines += [f"**What the other source views add to {kind}**: `{own_view_name(kind)}` is the same model at the "
                  f"same operating point, {how}: F1@{iou} {own['strict'][iou]['f1']:.3f} against "
                  f"{summaries[kind]['strict'][iou]['f1']:.3f} with every source view; recall on hidden-but-seen "
                  f"objects {_fmt(own_hs)} against {_fmt(full_hs)}. Whatever it finds of objects hidden in its own "
                  "view without the other views comes from what one image suggests, not from seeing them.", ""]
    return lines


def _late_fusion_lines(summaries: dict, iou: str) -> list[str]:
    late = summaries.get(late_fusion_name(BEV))
    if late is None:
        return []
    hs, _ = _recall(late, iou, HIDDEN_SEEN)
    sent, feats = late.get("bytes_per_car_frame"), late.get("feature_bytes_per_car_frame")
    size = "" if sent is None else (f" A car sends {sent:.0f} bytes per frame (its detections: a {HEADER_BYTES}-byte "
                                    f"header and {DETECTION_BYTES} bytes each, pnyolo.evaluation.message)")
    size += "" if feats is None else f", against {feats / 2**20:.1f} MiB of encoder feature maps a multi-view model reads from its camera."
    return [f"**Late fusion** (`{late_fusion_name(BEV)}`): the {BEV} model run on every camera alone, each car's 3D "
            "detections pooled in the world frame (same-class centres within eval.centre_nms_m merged) and projected "
            f"into each target view: F1@{iou} {late['strict'][iou]['f1']:.3f}, hidden-but-seen recall {_fmt(hs)}."
            + size, ""]


def _model_table(summaries: dict, timings: dict, kinds: list[str]) -> list[str]:
    lines = ["| model | training (s) | threads | inference per frame (ms) | threads | distance error (m) |",
             "|---|---|---|---|---|---|"]
    for k in kinds:
        s = summaries[k]
        de = s.get("distance_error", {}).get("mean_abs_m")
        ms = s.get("inference_ms")
        lines.append(f"| {k} | {_seconds(timings.get(f'train {k}'))} | {s.get('train_threads') or '-'} | "
                     f"{'-' if ms is None else f'{ms:.0f}'} | {s.get('inference_threads') or '-'} | "
                     f"{'-' if de is None else f'{de:.2f}'} |")
    return lines + [""]


def _sweep_rows(run: BenchRun) -> dict:
    """The pose-noise sweep's rows: this run's (a model trained with pose noise named so), then those
    of the runs set beside it."""
    own = {n: s["pose_noise_sweep"] for n, s in run.summaries.items() if "pose_noise_sweep" in s}
    rows = trained_with_noise(own, {k: m.config.train.pose_noise for k, m in run.models.items()})
    for label, path in run.beside.items():
        rows |= read_sweep(path, run.preset, label)
    return rows


def write_report(run: BenchRun) -> dict:
    """The run's comparison (every model's figures), report.md and report.json in ``run.report``,
    rendered from the record alone; returns report.json's content."""
    preset, summaries, timings, stats, report = run.preset, run.summaries, run.timings, run.statistics, run.report
    write_comparison(summaries, report, {"checkpoints": {k: str(m.checkpoint) for k, m in run.models.items()}})
    for kind, m in run.models.items():
        summaries[kind]["train_threads"] = m.training.get("threads")
    anchors = "" if run.anchors is None else str(run.anchors)
    iou = preset.iou
    kinds = [k for k in preset.models if k in summaries]
    f1 = {k: s["strict"][iou]["f1"] for k, s in summaries.items()}
    checks = bench_targets(preset, summaries, timings, iou)
    targets = {k: ok for k, (ok, _) in checks.items()}
    recall_plot(summaries, report / "recall_by_visibility.png", iou)
    ceiling = summaries[kinds[0]]["single_view_ceiling"]
    lines = [f"# Occlusion benchmark: `{preset.name}` preset", "",
             f"{preset.description}.", "",
             f"Command: `{run.command}`  ", f"Seed: {run.seed}; models: {', '.join(kinds)}; training budget: {preset.steps} "
             f"steps per model; config `{preset.config}` {preset.config_text()}", "",
             *[f"- `{k}`: {model_class(k).description}" for k in kinds if k in MODEL_REGISTRY], "",
             f"Ground truth (every model): every car and pedestrian with in-frame fraction >= "
             f"{label_thresholds(preset).min_in_frame} and distance <= {preset.max_distance} m, *including fully "
             f"hidden ones*; {'anchors fitted to the training labels: ' + anchors if anchors else 'anchors from the config'}.",
             "Chosen on the validation split, the same procedure for every model: the checkpoint (the run's end "
             "`latest.pt` or its best-validation `best.pt`) and the encoder's batch-norm statistics outside "
             "training (`running` averages, or `item`: those of the views encoded together, as in every training "
             f"step) and, for a model decoded by 2D NMS, the NMS IoU (of {', '.join(str(n) for n in preset.nms_grid)})"
             + (f" and, for a model with distance estimates, the depth gap of depth-gated NMS (of "
                f"{', '.join('none' if g is None else f'{g:g} m' for g in preset.depth_gaps)})"
                if preset.depth_gaps != (None,) else "")
             + (f" and, for a model that renders rays, the depth peaks kept per ray (of "
                f"{', '.join(str(k) for k in preset.depth_peaks)})" if preset.depth_peaks != (1,) else "")
             + f" with the best F1@{iou} at its best confidence threshold, "
             f"then the threshold by the one-standard-error rule (the lowest threshold whose validation F1@{iou} is "
             "within one bootstrap standard error, validation scenarios resampled, of the best): "
             + ", ".join(_selection_text(k, s, iou) for k, s in summaries.items() if "selection" in s) + ".",
             "",
             f"Scored on validation and test: {preset.scored_text(run.num_views)}.",
             "",
             "## Data", "",
             "| split | scenarios | images (views x lighting) | labels per lighting | fully hidden labels |",
             "|---|---|---|---|---|"]
    for split in ("train", "val", "test"):
        st = stats[split]
        lines.append(f"| {split} | {', '.join(st['scenarios'])} | {st['images']} | {st['labels_per_lighting']} | "
                     f"{st['fully_hidden_labels']} |")
    lines += ["", "## Results on the held-out scenarios", "",
              "![F1 versus match IoU](f1_vs_match_iou.png) ![recall by visibility](recall_by_visibility.png)", "",
              comparison_markdown(summaries), "",
              *(["`fusion`: the union of pixelnerf-yolo's and single-view's detections after NMS (the paper's "
                 "Table 6.11).", ""] if FUSION in summaries else []),
              *_own_view_lines(summaries, iou), *_late_fusion_lines(summaries, iou),
              f"**Single-view ceiling** (share of test ground truth with any visible pixel in its own view): "
              f"{ceiling['recall_ceiling']:.3f} of {ceiling['n']} ({ceiling['fully_hidden']} fully hidden). "
              "No single-view detector can exceed this recall.", "",
              *robustness_lines(_sweep_rows(run), report, iou)]
    for kind in multi_view_kinds(summaries):
        cov = summaries.get(kind, {}).get("coverage")
        if cov:
            where = ("the query points of the cell each road user's target is assigned to" if kind == MULTI else
                     "the pillar points of the grid cell holding each road user's centre")
            lines += [f"**Sampling coverage** of {kind} on the test split: over {where}, the share with a point "
                      "inside its 3D box, one projecting onto its visible pixels in a source view that sees it, and "
                      "one within one feature cell (the encoder's finest stride) of them.", "", coverage_markdown(cov)]
    enc = summaries.get(MULTI, {}).get("encoding_ceiling")
    if enc:
        hs_enc = enc["breakdown"].get(HIDDEN_SEEN, {}).get("recall")
        gap = f", depth gap {enc['depth_gap']:g} m with exact distances" if enc.get("depth_gap") is not None else ""
        lines += [f"**Encoding ceiling** of {MULTI} (a perfect detector: the test targets decoded and NMS-ed at "
                  f"{enc['nms_iou']}{gap} like its outputs): recall@{iou} {enc['recall']:.3f}, on hidden-but-seen "
                  f"objects {_fmt(hs_enc)}. Objects sharing a grid cell beyond its anchors, or suppressed by NMS "
                  "with their occluder, are lost to any model decoded that way.", ""]
    fp_table = false_positive_markdown(summaries, iou)
    if fp_table:
        lines += [fp_table]
    val_sweeps = {k: s["selection"]["val_sweep"] for k, s in summaries.items() if "val_sweep" in s.get("selection", {})}
    test_sweeps = {k: s["test_threshold_sweep"] for k, s in summaries.items() if "test_threshold_sweep" in s}
    if val_sweeps or test_sweeps:
        lines += [f"Every candidate confidence threshold (each model at its chosen NMS IoU), F1@{iou} / recall@{iou} "
                  "on hidden-but-seen objects, on the validation split (where the thresholds were chosen) and, for "
                  "information only, on the test split.",
                  "", _sweep_table(preset.conf_grid, {f"{k} (val)": v for k, v in val_sweeps.items()}
                                   | {f"{k} (test)": v for k, v in test_sweeps.items()}), ""]
    hidden_point = None
    anchor = best_multi_view(summaries)
    if anchor and "val_sweep" in summaries[anchor].get("selection", {}) and "test_threshold_sweep" in summaries[anchor]:
        hidden_point = hidden_target_point(summaries[anchor]["selection"]["val_sweep"],
                                           summaries[anchor]["test_threshold_sweep"], preset.hidden_recall_target)
        lines += [f"({anchor})"] + _hidden_target_lines(hidden_point, f1.get(SINGLE, float("nan")), iou)
    lines += ["## Models: training and inference", "",
              "Inference: forward pass and decoding of one frame (data.num_views views), evaluation mode, the "
              "median over 12 test items on this machine.", "", *_model_table(summaries, timings, kinds)]
    lines += ["## Targets", ""]
    for name, (ok, figures) in checks.items():
        lines.append(f"- {'PASS' if ok else ('n/a' if ok is None else 'FAIL')}: {name}: {figures}")
    lines += ["", "## Timings (seconds, this machine)", "", "| stage | seconds |", "|---|---|"]
    for k, v in timings.items():
        lines.append(f"| {k} | {_seconds(v)} |")
    examples = _one_per_scenario_first(sorted((report / "examples").glob("*.png")), preset.test)
    if examples:
        lines += ["", "## Where the multi-view model finds what the single view cannot", "",
                  "Each picture: the first model's detections (top rows) and the second's (bottom), on the same "
                  "source views; see `examples/`.", ""]
        lines += [f"![{p.stem}](examples/{p.name})" for p in examples[:4]]
    text = "\n".join(lines) + "\n"
    atomic_write_text(report / "report.md", text)
    hidden = {k: _recall(summaries[k], iou, HIDDEN_SEEN)[0] for k in summaries}
    result = {"preset": asdict(preset), "seed": run.seed, "command": run.command, "timings": timings, "dataset": stats,
              "targets": targets, "target_figures": {k: fig for k, (_, fig) in checks.items()}, f"f1_at_{iou}": f1,
              "hidden_seen_elsewhere_recall": {**hidden, "n": _recall(summaries[kinds[0]], iou, HIDDEN_SEEN)[1]},
              "single_view_ceiling": ceiling, "hidden_target_point": hidden_point, "models": summaries,
              **({"pose_noise_beside": {k: str(v) for k, v in run.beside.items()}} if run.beside else {})}
    atomic_write_json(report / "report.json", result)
    return result
