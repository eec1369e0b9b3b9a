"""The benchmark report: ``report.md`` with pictures and ``report.json`` with every figure.

    result = write_report(preset, summaries, timings, dataset_statistics(data, preset), report_dir, command, seed)
    result["targets"]      # {target text: True / False / None (nothing to measure)}
"""
from __future__ import annotations

import textwrap
from dataclasses import asdict
from pathlib import Path

from dataset_spec.atomic import atomic_write_json, atomic_write_text
from pnyolo.bench.presets import MULTI, SINGLE, BenchPreset
from pnyolo.bench.selection import hidden_target_point
from pnyolo.bench.stages import label_thresholds, model_config
from pnyolo.evaluation.coverage import coverage_markdown
from pnyolo.evaluation.metrics import HIDDEN_SEEN_ELSEWHERE as HIDDEN_SEEN

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
    fig.savefig(path, dpi=110)
    plt.close(fig)


# Targets of the world-space multi-view model (what the other cameras must add, and its sampling).
OWN_VIEW_MARGIN = 0.2  # hidden-but-seen recall at least this much above the own-view-only ablation
COVERAGE_TARGETS = {"on_pixels": 0.5, "near_pixels": 0.9, "in_box": 0.9}  # hidden-but-seen, every class


def world_space_targets(summaries: dict, iou: str) -> dict[str, bool | None]:
    """PASS/FAIL of the other views' contribution and of the sampling coverage (None: nothing measured)."""
    from pnyolo.evaluation.evaluate import own_view_name

    out: dict[str, bool | None] = {}
    own = summaries.get(own_view_name(MULTI))
    if own is not None:
        full_hs, own_hs = (_recall(s, iou, HIDDEN_SEEN)[0] for s in (summaries[MULTI], own))
        out[f"multi-view hidden-but-seen recall >= own view only + {OWN_VIEW_MARGIN:g}"] = (
            None if full_hs is None or own_hs is None else full_hs >= own_hs + OWN_VIEW_MARGIN)
    for cls, groups in summaries[MULTI].get("coverage", {}).items():
        rec = groups["hidden-but-seen"]
        for m, target in COVERAGE_TARGETS.items():
            out[f"coverage of hidden-but-seen {cls}s: {m.replace('_', ' ')} >= {target:g}"] = (
                None if rec[m] is None else rec[m] >= target)
    return out


def _own_view_lines(summaries: dict, iou: str) -> list[str]:
    """The report's paragraph on the multi-view model with each view's own image alone (if evaluated)."""
    from pnyolo.evaluation.evaluate import own_view_name

    own = summaries.get(own_view_name(MULTI))
    if own is None:
        return []
    full_hs, own_hs = (_recall(s, iou, HIDDEN_SEEN)[0] for s in (summaries[MULTI], own))
    return [f"**What the other source views add**: `{own_view_name(MULTI)}` is the same multi-view model at the "
            "same threshold and NMS, each view's rays sampling only that view's image features (the views are "
            f"still encoded together): F1@{iou} {own['strict'][iou]['f1']:.3f} against "
            f"{summaries[MULTI]['strict'][iou]['f1']:.3f} with every source view; recall on hidden-but-seen "
            f"objects {_fmt(own_hs)} against {_fmt(full_hs)}. Whatever it finds of objects hidden in its own "
            "view without the other views comes from what one image suggests, not from seeing them.", ""]


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


def _selection_text(kind: str, summary: dict) -> str:
    sel = summary["selection"]
    stats = f", {sel['eval_stats']} batch-norm statistics" if "eval_stats" in sel else ""
    stats += f", NMS IoU {sel['nms_iou']}" if "nms_iou" in sel else ""
    stats += f", depth gap {sel['depth_gap']:g} m" if sel.get("depth_gap") is not None else ""
    stats += f", {sel['depth_peaks']} depth peaks" if sel.get("depth_peaks", 1) > 1 else ""
    text = f"{kind} `{sel['checkpoint']}` (step {sel['step']}{stats}) at {summary['conf_threshold']:.2f}"
    if "best_threshold" in sel:
        text += (f" (validation F1@0.2 {sel['val_f1']:.3f}; best {sel['best_val_f1']:.3f} at "
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


def write_report(preset: BenchPreset, summaries: dict, timings: dict, stats: dict, report: Path, command: str,
                 seed: int, anchors: str = "") -> dict:
    iou = "0.2"
    mv, sv = summaries[MULTI], summaries[SINGLE]
    hs_mv, n_hs = _recall(mv, iou, HIDDEN_SEEN)
    hs_sv, _ = _recall(sv, iou, HIDDEN_SEEN)
    f1 = {k: s["strict"][iou]["f1"] for k, s in summaries.items()}
    targets = {
        f"multi-view recall on objects hidden in the target view but seen in another (IoU {iou}) >= "
        f"{preset.hidden_recall_target:g}": None if hs_mv is None else hs_mv >= preset.hidden_recall_target,
        f"multi-view F1@{iou} > single-view F1@{iou}": f1[MULTI] > f1[SINGLE],
        **world_space_targets(summaries, iou),
    }
    recall_plot(summaries, report / "recall_by_visibility.png", iou)
    ceiling = mv["single_view_ceiling"]
    lines = [f"# Occlusion benchmark: `{preset.name}` preset", "",
             f"{preset.description}.", "",
             f"Command: `{command}`  ", f"Seed: {seed}; training budget: {preset.steps} steps per model; "
             f"config `{preset.config}` {preset.config_text()}", "",
             f"Ground truth (both models): every car and pedestrian with in-frame fraction >= "
             f"{label_thresholds(preset).min_in_frame} and distance <= {preset.max_distance} m, *including fully "
             f"hidden ones*; {'anchors fitted to the training labels: ' + anchors if anchors else 'anchors from the config'}.",
             "Chosen on the validation split, the same procedure for both models: the checkpoint (the run's end "
             "`latest.pt` or its best-validation `best.pt`) and the encoder's batch-norm statistics outside "
             "training (`running` averages, or `item`: those of the views encoded together, as in every training "
             f"step) and the NMS IoU (of {', '.join(str(n) for n in preset.nms_grid)})"
             + (f" and, for a model with distance estimates, the depth gap of depth-gated NMS (of "
                f"{', '.join('none' if g is None else f'{g:g} m' for g in preset.depth_gaps)})"
                if preset.depth_gaps != (None,) else "")
             + (f" and, for a model that renders rays, the depth peaks kept per ray (of "
                f"{', '.join(str(k) for k in preset.depth_peaks)})" if preset.depth_peaks != (1,) else "")
             + " with the best F1@0.2 at its best confidence threshold, "
             "then the threshold by the one-standard-error rule (the lowest threshold whose validation F1@0.2 is "
             "within one bootstrap standard error, validation scenarios resampled, of the best): "
             + ", ".join(_selection_text(k, s) for k, s in summaries.items() if "selection" in s) + ".",
             "",
             f"Scored on validation and test: {preset.scored_text(model_config(preset, MULTI, None, seed).data.num_views)}.",
             "",
             "## Data", "",
             "| split | scenarios | images (views x lighting) | labels per lighting | fully hidden labels |",
             "|---|---|---|---|---|"]
    for split in ("train", "val", "test"):
        s = stats[split]
        lines.append(f"| {split} | {', '.join(s['scenarios'])} | {s['images']} | {s['labels_per_lighting']} | "
                     f"{s['fully_hidden_labels']} |")
    lines += ["", "## Results on the held-out scenarios", "",
              f"![F1 versus match IoU](f1_vs_match_iou.png) ![recall by visibility](recall_by_visibility.png)", "",
              (report / "comparison.md").read_text(), "",
              *_own_view_lines(summaries, iou),
              f"**Single-view ceiling** (share of test ground truth with any visible pixel in its own view): "
              f"{ceiling['recall_ceiling']:.3f} of {ceiling['n']} ({ceiling['fully_hidden']} fully hidden). "
              "No single-view detector can exceed this recall.", ""]
    if mv.get("coverage"):
        lines += [f"**Sampling coverage** of the multi-view model on the test split: over the query points of the "
                  "cell each road user's target is assigned to, the share with a point inside its 3D box, one "
                  "projecting onto its visible pixels in a source view that sees it, and one within one feature cell "
                  "(the encoder's finest stride) of them.", "", coverage_markdown(mv["coverage"])]
    enc = mv.get("encoding_ceiling")
    if enc:
        hs_enc = enc["breakdown"].get(HIDDEN_SEEN, {}).get("recall")
        gap = f", depth gap {enc['depth_gap']:g} m with exact distances" if enc.get("depth_gap") is not None else ""
        lines += [f"**Encoding ceiling** (a perfect detector: the test targets decoded and NMS-ed at "
                  f"{enc['nms_iou']}{gap} like the multi-view model's outputs): recall@{iou} {enc['recall']:.3f}, on hidden-but-seen "
                  f"objects {_fmt(hs_enc)}. Objects sharing a grid cell beyond "
                  "its anchors, or suppressed by NMS with their occluder, are lost to any model.", ""]
    from pnyolo.evaluation.report import false_positive_markdown

    fp_table = false_positive_markdown(summaries, iou)
    if fp_table:
        lines += [fp_table]
    val_sweeps = {k: s["selection"]["val_sweep"] for k, s in summaries.items() if "val_sweep" in s.get("selection", {})}
    test_sweeps = {k: s["test_threshold_sweep"] for k, s in summaries.items() if "test_threshold_sweep" in s}
    if val_sweeps or test_sweeps:
        lines += [f"Every candidate confidence threshold (each model at its chosen NMS IoU), F1@{iou} / recall@{iou} "
                  "on hidden-but-seen objects, on the validation split (where the thresholds were chosen) and, for information only, on the test split.",
                  "", _sweep_table(preset.conf_grid, {f"{k} (val)": v for k, v in val_sweeps.items()}
                                   | {f"{k} (test)": v for k, v in test_sweeps.items()}), ""]
    hidden_point = None
    if "val_sweep" in mv.get("selection", {}) and "test_threshold_sweep" in mv:
        hidden_point = hidden_target_point(mv["selection"]["val_sweep"], mv["test_threshold_sweep"],
                                           preset.hidden_recall_target)
        lines += _hidden_target_lines(hidden_point, f1[SINGLE], iou)
    de = mv.get("distance_error", {})
    if de.get("mean_abs_m") is not None:
        lines.append(f"**Distance estimate** (multi-view, confidence-weighted depth along the ray): mean absolute error "
                     f"{de['mean_abs_m']:.2f} m over {de['n']} matched detections.")
    lines += ["", "## Targets", ""]
    for name, ok in targets.items():
        lines.append(f"- {'PASS' if ok else ('n/a' if ok is None else 'FAIL')}: {name}")
    lines += ["", f"Measured: multi-view recall on hidden-but-seen-elsewhere objects "
              f"{_fmt(hs_mv)} (n = {n_hs}); single view "
              f"{_fmt(hs_sv)}. F1@{iou}: "
              + ", ".join(f"{k} {v:.3f}" for k, v in f1.items()) + ".",
              "", "## Timings (seconds, this machine)", "", "| stage | seconds |", "|---|---|"]
    for k, v in timings.items():
        lines.append(f"| {k} | {_seconds(v)} |")
    examples = _one_per_scenario_first(sorted((report / "examples").glob("*.png")), preset.test)
    if examples:
        lines += ["", "## Where the multi-view model finds what the single view cannot", "",
                  "Each picture: the multi-view model's detections (top rows) and the single-view model's (bottom), "
                  "on the same source views; see `examples/`.", ""]
        lines += [f"![{p.stem}](examples/{p.name})" for p in examples[:4]]
    text = "\n".join(lines) + "\n"
    atomic_write_text(report / "report.md", text)
    result = {"preset": asdict(preset), "seed": seed, "command": command, "timings": timings, "dataset": stats,
              "targets": {k: v for k, v in targets.items()}, "f1_at_0.2": f1,
              "hidden_seen_elsewhere_recall": {MULTI: hs_mv, SINGLE: hs_sv, "n": n_hs},
              "single_view_ceiling": ceiling, "hidden_target_point": hidden_point, "models": summaries}
    atomic_write_json(report / "report.json", result)
    return result


