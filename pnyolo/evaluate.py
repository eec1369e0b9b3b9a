"""Evaluation shared by training (validation) and ``pnyolo-eval``: same code, same numbers.

Example::

    acc = evaluate_dataset(model, MultiViewDataset(root, "test", cfg, views=[0, 1, 2]), cfg)
    summary = acc.summary()
    write_report(summary, "out/eval", cfg)

    # two detectors on the same items and source views, plus their fusion (issue 6)
    accs = evaluate_models({"multi-view": (mv, mv_cfg), "single-view": (sv, sv_cfg)}, dataset, fuse=True)
    write_comparison(accs_to_summaries(accs), "out/compare")
"""
from __future__ import annotations

from pathlib import Path

import torch

from dataset_spec.atomic import atomic_write_json, atomic_write_text

from .config import Config
from .data import MultiViewDataset
from .metrics import MetricAccumulator, ViewGroundTruth, match_strict
from .fusion import fuse_detections
from .postprocess import decode_outputs, decode_with
from .renderer import RayOutputs
from .targets import perfect_raw
from .vis import panel, write_png

FUSION = "fusion"


def own_view_name(model_name: str) -> str:
    """The accumulator name of ``model_name`` evaluated with each view's own image alone."""
    return f"{model_name}, own view only"


def predict_item(model, item: dict, device, ray_mask=None, own_view_only: bool = False,
                 drop_own_view=None) -> "object":
    """The model's outputs for one item's views (``ray_mask``: render only these cells and
    ``drop_own_view``: these cells without their own view's features, see ``pnyolo.ray_selection``;
    ``own_view_only``: each view from its own image features alone, the other source views dropped,
    see ``PixelNeRFYolo.forward``)."""
    return model(item["images"].to(device), item["K"].to(device), item["camera_to_world"].to(device), item["grid"],
                 ray_mask=ray_mask, own_view_only=own_view_only, drop_own_view=drop_own_view)


@torch.no_grad()
def evaluate_dataset(model, dataset: MultiViewDataset, cfg: Config, device="cpu", example_dir: str | Path | None = None,
                     max_examples: int = 0) -> MetricAccumulator:
    was_training = model.training
    model.eval()
    acc = MetricAccumulator(cfg.eval.match_ious, len(dataset.class_names))
    for k in range(len(dataset)):
        item = dataset[k]
        out = predict_item(model, item, device)
        dets = decode_with(out, model.anchors, item["grid"], cfg.eval)
        for _, det, gt in scored_views(item, dets):
            acc.add(det, gt)
        if example_dir is not None and k < max_examples:
            write_png(Path(example_dir) / f"{item_name(item)}.png",
                      panel(item, dets, dataset.class_names))
    model.train(was_training)
    return acc


def encoding_ceiling(dataset: MultiViewDataset, anchors: torch.Tensor, nms_iou: float, iou: float = 0.2,
                     depth_gap: float | None = None) -> dict:
    """Recall of a *perfect* detector: each item's YOLO targets turned back into outputs
    (``targets.perfect_raw``, exact distances), decoded and NMS-ed like any model's (``depth_gap``:
    depth-gated NMS), matched at ``iou``.

    Objects that lose their target slot (several in one cell) or are suppressed by NMS (amodal
    boxes of a hidden object and its occluder overlapping) count as misses: no model trained on
    these targets and decoded this way can exceed this. Returns overall recall and the recall
    breakdown (visibility bins, hidden-but-seen-elsewhere).
    """
    acc = MetricAccumulator((iou,), len(dataset.class_names))
    for k in range(len(dataset)):
        item = dataset[k]
        out = RayOutputs(**perfect_raw(item["targets"], anchors.cpu(), len(dataset.class_names)))
        for _, det, gt in scored_views(item, decode_outputs(out, anchors.cpu(), item["grid"], 0.5, nms_iou, depth_gap)):
            acc.add(det, gt)
    counts = acc.counts(iou)
    return {"match_iou": iou, "nms_iou": nms_iou, "depth_gap": depth_gap, "recall": counts["recall"],
            "n": counts["tp"] + counts["fn"], "breakdown": acc.recall_breakdown(iou)}


def _ground_truth(gt: dict) -> ViewGroundTruth:
    return ViewGroundTruth(gt["boxes"], gt["classes"], gt["visible_fraction"], gt["seen_elsewhere"], gt["distances"],
                           gt.get("excluded_boxes"))


def item_name(item: dict) -> str:
    """SCENARIO_VARIANT_camCAMERAS, e.g. ``intersection_07_dusk_cam3-4-0``: an item's pictures are
    told apart from those of the scene's other camera groups."""
    return f"{item['scenario']}_{item['variant']}_cam{'-'.join(str(v) for v in item['views'])}"


def scored_views(item: dict, dets: list) -> list[tuple[int, object, ViewGroundTruth]]:
    """(view position, its detections, its ground truth) for each view of the item that evaluation
    scores (``item["scored"]``; a view serving only as a source is left out), ``dets`` one per view."""
    return [(v, dets[v], _ground_truth(item["gt"][v])) for v in item["scored"]]


def spread_over_scenarios(items: list[tuple]) -> list[int]:
    """Indices of dataset items (tuples starting with the scenario), each scenario's first item
    before any second one (stable otherwise): the first few items visited cover the most scenarios."""
    seen: dict[str, int] = {}
    rank = []
    for k, (scenario, *_) in enumerate(items):
        rank.append((seen.get(scenario, 0), k))
        seen[scenario] = seen.get(scenario, 0) + 1
    return [k for _, k in sorted(rank)]


@torch.no_grad()
def evaluate_models(models: dict[str, tuple], dataset: MultiViewDataset, device="cpu", fuse: bool = False,
                    example_dir: str | Path | None = None, max_examples: int = 0,
                    own_view: tuple[str, ...] = ()) -> dict[str, MetricAccumulator]:
    """Evaluate several detectors on the same items and source views.

    ``models`` maps a name to ``(model, cfg)``; each model decodes with its own config's thresholds.
    With ``fuse`` (exactly two models) a third accumulator ``"fusion"`` holds the union of both
    detectors' detections after NMS at the first model's ``eval.nms_iou`` and ``eval.depth_gap`` (the
    paper's Table 6.11).
    Each model named in ``own_view`` is also evaluated with every view's rays seeing only that
    view's image features (``own_view_name(name)``: what the other source views add).
    With ``example_dir``, writes up to ``max_examples`` panels of views where the first model finds
    a ground-truth object that the second misses (at match IoU ``eval.select_iou`` of the first).
    """
    names = list(models)
    if fuse and len(names) != 2:
        raise ValueError("fusion needs exactly two models")
    first_cfg = models[names[0]][1]
    accs = {n: MetricAccumulator(first_cfg.eval.match_ious, len(dataset.class_names))
            for n in [*names, *([FUSION] if fuse else []), *map(own_view_name, own_view)]}
    direct = [n for n in accs if n != FUSION]  # fed each model's own detections (fusion: the union, below)
    was_training = {n: m.training for n, (m, _) in models.items()}
    for m, _ in models.values():
        m.eval()
    written = 0
    for k in spread_over_scenarios(dataset.items):  # example pictures from as many streets as possible
        item = dataset[k]
        dets = {}
        for n, (m, cfg) in models.items():
            dets[n] = decode_with(predict_item(m, item, device), m.anchors, item["grid"], cfg.eval)
        for n in own_view:
            m, cfg = models[n]
            dets[own_view_name(n)] = decode_with(predict_item(m, item, device, own_view_only=True), m.anchors,
                                                 item["grid"], cfg.eval)
        views = scored_views(item, dets[names[0]])  # ground truth built once, for metrics and examples
        for v, _, gt in views:
            for n in direct:
                accs[n].add(dets[n][v], gt)
            if fuse:
                accs[FUSION].add(fuse_detections(dets[names[0]][v], dets[names[1]][v], first_cfg.eval.nms_iou,
                                                 depth_gap=first_cfg.eval.depth_gap), gt)
        if example_dir is not None and len(names) >= 2 and written < max_examples:
            iou = first_cfg.eval.select_iou
            gains = [v for v, first, gt in views
                     if (match_strict(first, gt, iou)[1] & ~match_strict(dets[names[1]][v], gt, iou)[1]).any()]
            if gains:
                rows = [panel(item, dets[n], dataset.class_names) for n in names]
                write_png(Path(example_dir) / f"{item_name(item)}_{names[0]}_vs_{names[1]}.png",
                          _stack_rows(rows, [f"{n}" for n in names]))
                written += 1
    for n, (m, _) in models.items():
        m.train(was_training[n])
    return accs


def _stack_rows(rows: list, titles: list[str]):
    import cv2
    import numpy as np

    width = max(r.shape[1] for r in rows)
    out = []
    for r, t in zip(rows, titles):
        bar = np.full((18, width, 3), 255, np.uint8)
        cv2.putText(bar, t, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        pad = np.full((r.shape[0], width - r.shape[1], 3), 255, np.uint8)
        out += [bar, np.concatenate([r, pad], axis=1)]
    return np.concatenate(out, axis=0)


def comparison_markdown(summaries: dict[str, dict], iou_for_bins: str = "0.2") -> str:
    """Side-by-side precision/recall/F1 per match IoU, and recall per visibility bin, for several models."""
    names = list(summaries)
    ious = list(next(iter(summaries.values()))["strict"])
    head = "| match IoU | " + " | ".join(f"{n} P | {n} R | {n} F1" for n in names) + " |"
    lines = [head, "|" + "---|" * (1 + 3 * len(names))]
    for t in ious:
        cells = [f"{summaries[n]['strict'][t]['precision']:.3f} | {summaries[n]['strict'][t]['recall']:.3f} | "
                 f"**{summaries[n]['strict'][t]['f1']:.3f}**" for n in names]
        lines.append(f"| {t} | " + " | ".join(cells) + " |")
    lines += ["", f"AP50: " + ", ".join(f"{n} {summaries[n]['ap50']:.3f}" for n in names),
              f"AP50:95: " + ", ".join(f"{n} {summaries[n]['ap50_95']:.3f}" for n in names), ""]
    groups = []
    for n in names:
        for g in summaries[n]["recall_by_visibility"].get(iou_for_bins, {}):
            if g not in groups:
                groups.append(g)
    lines += [f"Recall at match IoU {iou_for_bins} by ground-truth group (target-view visibility; whether another "
              "source view sees the object):", "", "| group | n | " + " | ".join(names) + " |",
              "|" + "---|" * (2 + len(names))]
    for g in groups:
        rec = [summaries[n]["recall_by_visibility"].get(iou_for_bins, {}).get(g) for n in names]
        n_gt = next((r["n"] for r in rec if r), 0)
        lines.append(f"| {g} | {n_gt} | " + " | ".join(f"{r['recall']:.3f}" if r else "-" for r in rec) + " |")
    return "\n".join(lines) + "\n"


FALSE_POSITIVE_NOTE = ("*On a ground-truth object*: a duplicate, a wrong class or a box given to another detection; "
                       "*near an object*: overlapping a labelled road user, but too little; "
                       "*on no labelled object*: nothing there (for the multi-view model typically a ray crossing "
                       "another view's object away from its true depth). *Ignored*: detections of road users "
                       "outside the ground truth (too far or too truncated), neither true nor false positives.")


def false_positive_markdown(summaries: dict[str, dict], iou: str = "0.2") -> str:
    """Where each model's unmatched detections lie (``MetricAccumulator.false_positive_breakdown``)."""
    fps = {k: s["false_positives"][iou] for k, s in summaries.items() if iou in s.get("false_positives", {})}
    if not fps:
        return ""
    cats = [c for c, v in next(iter(fps.values())).items() if isinstance(v, dict)]
    lines = [f"Where the unmatched detections (false positives at match IoU {iou}) lie:", "",
             "| false positives | " + " | ".join(fps) + " |", "|---|" + "---|" * len(fps),
             "| all | " + " | ".join(str(f["n"]) for f in fps.values()) + " |"]
    lines += [f"| {c} | " + " | ".join(f"{f[c]['count']} ({f[c]['share']:.0%})" for f in fps.values()) + " |"
              for c in cats]
    lines.append("| ignored (on an excluded object; not in *all*) | "
                 + " | ".join(str(f["ignored"]) for f in fps.values()) + " |")
    return "\n".join(lines + ["", FALSE_POSITIVE_NOTE, ""])


def comparison_plot(summaries: dict[str, dict], path: str | Path, mode: str = "strict") -> None:
    """F1 versus match IoU for several models (the paper's Figure 6.6)."""
    plot_f1_curves({name: s[mode] for name, s in summaries.items()}, path, f"F1 ({mode})")


def plot_f1_curves(curves: dict[str, dict], path: str | Path, ylabel: str = "F1") -> None:
    """One line per entry of ``curves`` ({label: {match IoU: {"f1": ...}}}), F1 against match IoU."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for label, by_iou in curves.items():
        ax.plot([float(t) for t in by_iou], [m["f1"] for m in by_iou.values()], marker="o", label=label)
    ax.set_xlabel("match IoU threshold")
    ax.set_ylabel(ylabel)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_comparison(summaries: dict[str, dict], out_dir: str | Path, extra: dict | None = None) -> None:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name, summary in summaries.items():
        write_report(summary, out / name, extra)
    atomic_write_json(out / "comparison.json", {**(extra or {}), "models": summaries})
    atomic_write_text(out / "comparison.md", comparison_markdown(summaries))
    comparison_plot(summaries, out / "f1_vs_match_iou.png")


def markdown_table(summary: dict) -> str:
    lines = ["| match IoU | mode | precision | recall | F1 | TP | FP | FN |", "|---|---|---|---|---|---|---|---|"]
    for mode in ("strict", "paper"):
        for t, m in summary[mode].items():
            lines.append(f"| {t} | {mode} | {m['precision']:.4f} | {m['recall']:.4f} | {m['f1']:.4f} | "
                         f"{m['tp']} | {m['fp']} | {m['fn']} |")
    lines += ["", f"AP50 {summary['ap50']:.4f} · AP50:95 {summary['ap50_95']:.4f} · views {summary['views']} · "
              f"ground truth {summary['ground_truth']} · predictions {summary['predictions']}", ""]
    rv = summary["recall_by_visibility"]
    key = "0.4" if "0.4" in rv else next(iter(rv), None)
    if key:
        lines += [f"Recall at match IoU {key} (strict) by ground truth group:", "", "| group | recall | n |", "|---|---|---|"]
        lines += [f"| {g} | {v['recall']:.4f} | {v['n']} |" for g, v in rv[key].items()]
        lines += ["", false_positive_markdown({"detections": summary}, key)]
    de = summary.get("distance_error", {})
    if de.get("mean_abs_m") is not None:
        lines += ["", f"Distance estimate: mean absolute error {de['mean_abs_m']:.2f} m over {de['n']} matched detections"]
    return "\n".join(lines) + "\n"


def f1_plot(summary: dict, path: str | Path) -> None:
    """F1 versus match IoU of one model, in both counting modes."""
    plot_f1_curves({f"F1 ({mode})": summary[mode] for mode in ("strict", "paper")}, path)


def write_report(summary: dict, out_dir: str | Path, extra: dict | None = None) -> None:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "metrics.json", {**(extra or {}), **summary})
    atomic_write_text(out / "metrics.md", markdown_table(summary))
    f1_plot(summary, out / "f1_vs_match_iou.png")


def headline(summary: dict, iou: float, mode: str = "strict") -> float:
    return float(summary[mode][f"{iou:.1f}"]["f1"]) if f"{iou:.1f}" in summary[mode] else float("nan")


