"""Ultralytics YOLO layout: ``images/<split>/*.png``, ``labels/<split>/*.txt``, ``data.yaml``.

Each label line is ``class cx cy w h`` with the centre and size as fractions of the image
(``dataset_spec.boxes.box_to_yolo``), class = index in ``DatasetInfo.detectable_classes``.
Boxes are the amodal boxes clipped to the image; an image without kept labels gets an empty
file (a background image for Ultralytics). Fully hidden road users are exported as ordinary boxes
(the default ``min_visible`` is 0, which multi-view training wants); raise ``--min-visible`` for a
detector that should only learn what its image shows. The format has no ignore regions, so labels
the thresholds leave out are simply absent.

``data.yaml`` always has every key Ultralytics' ``check_det_dataset`` requires: ``path``, ``train``,
``val`` (each an existing folder), ``nc`` and ``names``; ``test`` when the dataset has a test split.
A split without images points at the training images (``val: images/train`` for a dataset without
validation scenarios; ``train`` at the first split that has images), so Ultralytics can start; the
file says so in a comment.

Usage::

    folder = export_yolo(ds, "out/exports/yolo")
    classes, boxes = read_yolo_labels(folder / "labels/train/toy_01__cam_0.txt", 64, 48)
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from dataset_spec import Dataset, LabelThresholds
from dataset_spec.atomic import atomic_write_text
from dataset_spec.boxes import box_to_yolo, yolo_to_box

from dataset_spec.cli_support import UserError
from dataset_spec.names import below

from .common import UNSPLIT, class_index, copy_file, export_views


def yolo_lines(labels, cls_index: dict[str, int], width: int, height: int) -> list[str]:
    """``class cx cy w h`` lines (normalised, 6 decimals) for labels of kept detectable classes."""
    lines = []
    for o in labels:
        if o.cls not in cls_index:
            continue
        cx, cy, w, h = np.clip(box_to_yolo(o.box, width, height), 0.0, 1.0)
        lines.append(f"{cls_index[o.cls]} {cx:.6f} {cy:.6f} {w:.6f} {h:.6f}")
    return lines


def export_yolo(ds: Dataset, out_dir: str | Path, scenarios: list[str] | None = None,
                thresholds: LabelThresholds | None = None, variant: str | None = None) -> Path:
    """Write the YOLO tree under ``out_dir``; returns ``out_dir``."""
    out = Path(out_dir)
    cls_index = class_index(ds)
    splits = set()
    for view in export_views(ds, scenarios, thresholds, variant):
        splits.add(view.split)
        copy_file(view.image_path, below(out, "images", view.split, f"{view.stem}.png"))
        lines = yolo_lines(view.labels, cls_index, view.camera.width, view.camera.height)
        atomic_write_text(below(out, "labels", view.split, f"{view.stem}.txt"), "".join(f"{x}\n" for x in lines))
    atomic_write_text(out / "data.yaml", data_yaml(out, splits, cls_index))
    return out


def data_yaml(out: Path, splits: set[str], cls_index: dict[str, int]) -> str:
    """``data.yaml`` text: every split Ultralytics needs, an empty one pointed at images that exist."""
    present = [s for s in ("train", "val", "test", UNSPLIT) if s in splits]
    if not present:
        raise UserError("nothing to export: the dataset has no views")
    train = "train" if "train" in splits else present[0]
    paths = {"train": f"images/{train}", "val": f"images/{'val' if 'val' in splits else train}"}
    if "test" in splits:
        paths["test"] = "images/test"
    notes = [f"# {k}: no {k} images in this dataset; pointed at {v} so Ultralytics can start"
             for k, v in paths.items() if v != f"images/{k}"]
    data = {"path": str(out.resolve()), **paths, "nc": len(cls_index), "names": {i: n for n, i in cls_index.items()}}
    return "".join(n + "\n" for n in notes) + yaml.safe_dump(data, sort_keys=False)


def read_yolo_labels(path: str | Path, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Read a YOLO label file -> (classes (N,) int, boxes (N, 4) [x0, y0, x1, y1] pixels)."""
    rows = [line.split() for line in Path(path).read_text().splitlines() if line.strip()]
    if any(len(r) != 5 for r in rows):
        raise ValueError(f"{path}: every line must have 5 columns")
    classes = np.array([int(r[0]) for r in rows], dtype=np.int64)
    boxes = np.array([yolo_to_box([float(x) for x in r[1:]], width, height) for r in rows]).reshape(-1, 4)
    return classes, boxes
