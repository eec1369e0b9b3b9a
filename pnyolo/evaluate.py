"""Evaluation shared by training (validation) and ``pnyolo-eval``: same code, same numbers.

Example::

    acc = evaluate_dataset(model, MultiViewDataset(root, "test", cfg, views=[0, 1, 2]), cfg)
    summary = acc.summary()
    write_report(summary, "out/eval", cfg)
"""
from __future__ import annotations

from pathlib import Path

import torch

from dataset_spec.atomic import atomic_write_json, atomic_write_text

from .config import Config
from .data import MultiViewDataset
from .metrics import MetricAccumulator, ViewGroundTruth
from .postprocess import decode_outputs
from .vis import panel, write_png


def predict_item(model, item: dict, device) -> "object":
    return model(item["images"].to(device), item["K"].to(device), item["camera_to_world"].to(device), item["grid"])


@torch.no_grad()
def evaluate_dataset(model, dataset: MultiViewDataset, cfg: Config, device="cpu", example_dir: str | Path | None = None,
                     max_examples: int = 0) -> MetricAccumulator:
    was_training = model.training
    model.eval()
    acc = MetricAccumulator(cfg.eval.match_ious, len(dataset.class_names))
    for k in range(len(dataset)):
        item = dataset[k]
        out = predict_item(model, item, device)
        dets = decode_outputs(out, model.anchors, item["grid"], cfg.eval.conf_threshold, cfg.eval.nms_iou)
        for det, gt in zip(dets, item["gt"]):
            acc.add(det, ViewGroundTruth(gt["boxes"], gt["classes"], gt["visible_fraction"], gt["seen_elsewhere"],
                                         gt["distances"]))
        if example_dir is not None and k < max_examples:
            write_png(Path(example_dir) / f"{item['scenario']}_{item['variant']}.png",
                      panel(item, dets, dataset.class_names))
    model.train(was_training)
    return acc


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
    de = summary.get("distance_error", {})
    if de.get("mean_abs_m") is not None:
        lines += ["", f"Distance estimate: mean absolute error {de['mean_abs_m']:.2f} m over {de['n']} matched detections"]
    return "\n".join(lines) + "\n"


def f1_plot(summary: dict, path: str | Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5))
    for mode in ("strict", "paper"):
        ts = [float(t) for t in summary[mode]]
        ax.plot(ts, [summary[mode][t]["f1"] for t in summary[mode]], marker="o", label=f"F1 ({mode})")
    ax.set_xlabel("match IoU threshold")
    ax.set_ylabel("F1")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_report(summary: dict, out_dir: str | Path, extra: dict | None = None) -> None:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "metrics.json", {**(extra or {}), **summary})
    atomic_write_text(out / "metrics.md", markdown_table(summary))
    f1_plot(summary, out / "f1_vs_match_iou.png")


def headline(summary: dict, iou: float, mode: str = "strict") -> float:
    return float(summary[mode][f"{iou:.1f}"]["f1"]) if f"{iou:.1f}" in summary[mode] else float("nan")


