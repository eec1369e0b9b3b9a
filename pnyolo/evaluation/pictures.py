"""Visualisations as PNG: per source view a row of (source view | target grid | GT | prediction)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from dataset_spec.atomic import atomic_path
from pnyolo.data.item import Item
from pnyolo.evaluation.metrics import ViewDetections

COLOURS = [(255, 80, 80), (80, 160, 255), (80, 220, 80), (240, 200, 60)]


def to_uint8(image: torch.Tensor) -> np.ndarray:
    """(3, H, W) in [0, 1] -> (H, W, 3) uint8 RGB."""
    return (image.detach().cpu().clamp(0, 1).permute(1, 2, 0).numpy() * 255).astype(np.uint8).copy()


def draw_boxes(img: np.ndarray, boxes, classes, scores=None, names=None, distances=None) -> np.ndarray:
    img = img.copy()
    for k, b in enumerate(np.asarray(boxes).reshape(-1, 4)):
        c = int(classes[k]) if len(classes) else 0
        col = COLOURS[c % len(COLOURS)]
        x0, y0, x1, y1 = (int(round(v)) for v in b)
        cv2.rectangle(img, (x0, y0), (x1, y1), col, 1)
        text = names[c] if names and c < len(names) else str(c)
        if scores is not None:
            text += f" {scores[k]:.2f}"
        if distances is not None and np.isfinite(distances[k]):
            text += f" {distances[k]:.0f}m"
        if img.shape[1] >= 200:
            cv2.putText(img, text, (x0, max(8, y0 - 2)), cv2.FONT_HERSHEY_SIMPLEX, 0.3, col, 1, cv2.LINE_AA)
    return img


def target_heatmap(target: torch.Tensor, shape) -> np.ndarray:
    """Targets (S_h, S_w, A, TARGET_CHANNELS) -> an image: cells with an object bright, ignored grey."""
    obj = target[..., 0].detach().cpu()
    cell = torch.where((obj == 1).any(-1), 1.0, torch.where((obj == -1).any(-1), 0.4, 0.0)).numpy()
    img = cv2.resize((cell * 255).astype(np.uint8), (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)
    return np.repeat(img[..., None], 3, axis=2)


def panel(item: Item, detections: list[ViewDetections], class_names: list[str] | None = None,
          targets=None) -> np.ndarray:
    """Per view: the image, its YOLO targets (``targets``, the model's; black without), the ground truth
    and the detections."""
    rows = []
    for v in range(item.images.shape[0]):
        src = to_uint8(item.images[v])
        gt = item.gt[v]
        tgt = target_heatmap(targets[v], src.shape) if targets is not None else np.zeros_like(src)
        d = detections[v]
        rows.append(np.concatenate([src, tgt, draw_boxes(src, gt.boxes, gt.classes, names=class_names),
                                    draw_boxes(src, d.boxes, d.classes, d.scores, class_names, d.distances)], axis=1))
    return np.concatenate(rows, axis=0)


def write_png(path: str | Path, rgb: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if ok:
        with atomic_path(path) as tmp:
            buf.tofile(tmp)


def stack_rows(rows: list, titles: list[str]) -> np.ndarray:
    """Pictures (H_k, W_k, 3) stacked top to bottom, each under a white bar with its title."""
    width = max(r.shape[1] for r in rows)
    out = []
    for r, t in zip(rows, titles):
        bar = np.full((18, width, 3), 255, np.uint8)
        cv2.putText(bar, t, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        pad = np.full((r.shape[0], width - r.shape[1], 3), 255, np.uint8)
        out += [bar, np.concatenate([r, pad], axis=1)]
    return np.concatenate(out, axis=0)
