"""Detections in the formats other tools read, and results of other detectors scored with ours.

    index = image_index(dataset.ds, variant="all")              # (scenario, camera, variant) -> (split, id)
    rows = coco_results(item, dets, index, class_ids)           # COCO results: image_id, category_id, bbox, score
    results = read_coco_results("yolo_results.json", dataset.ds, index)   # -> {view key: ViewDetections}
    acc = score_results(results, dataset, match_ious)           # the same metrics as for a checkpoint

Image ids are those of the project's COCO export of the same dataset (``tools.exporters.coco.
coco_image_ids``, every scenario, the same ``--variant``), so ``pycocotools.COCOeval`` scores a
results file against that export directly. Boxes are in the original images' pixels: COCO's
``[x, y, w, h]`` with pixel (0, 0) covering [0, 1] x [0, 1].
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dataset_spec import Dataset
from dataset_spec.cli_support import UserError
from pnyolo.evaluation.metrics import MetricAccumulator, ViewDetections
from tools.exporters.coco import box_from_coco, coco_bbox, coco_image_ids

ViewKey = tuple[str, str, str]  # (scenario, camera, lighting variant)


def image_index(ds: Dataset, variant: str | None = None) -> dict[ViewKey, tuple[str, int]]:
    """(scenario, camera, variant) -> (split, COCO image id), as the COCO export numbers them."""
    return coco_image_ids(ds, None, variant)


def to_original(boxes: np.ndarray, scale: tuple[float, float]) -> np.ndarray:
    """Boxes (N, 4) in an item's encoded pixels -> the original image's pixels (scale = encoded / original)."""
    sx, sy = scale
    s = np.array([sx, sy, sx, sy])
    return (np.asarray(boxes, dtype=np.float64).reshape(-1, 4) + 0.5) / s - 0.5


def view_scale(item: dict, v: int) -> tuple[float, float]:
    width, height = item["original_sizes"][v]
    return item["grid"].width / width, item["grid"].height / height


def coco_results(item: dict, dets: list[ViewDetections], index: dict[ViewKey, tuple[str, int]],
                 class_ids: list[int]) -> list[dict]:
    """COCO result rows of an item's scored views (``dets`` one per view, in encoded pixels)."""
    rows = []
    for v in item["scored"]:
        key = (item["scenario"], item["camera_names"][v], item["variant"])
        if key not in index:
            continue  # a lighting variant the index does not export (see --variant)
        image_id = index[key][1]
        d = dets[v]
        for box, score, cls in zip(to_original(d.boxes, view_scale(item, v)), d.scores, d.classes):
            rows.append({"image_id": image_id, "category_id": int(class_ids[int(cls)]),
                         "bbox": [round(x, 3) for x in coco_bbox(box)], "score": round(float(score), 5)})
    return rows


def view_record(item: dict, v: int, det: ViewDetections, class_names: list[str]) -> dict:
    """One view's detections as plain JSON: boxes [x0, y0, x1, y1] in the original pixels, distances,
    and for models with 3D boxes ``box_3d`` (world centre, length, width, height, yaw; SPEC.md)."""
    boxes = to_original(det.boxes, view_scale(item, v))
    dist = det.distances if det.distances is not None else np.full(len(boxes), np.nan)
    rows = [{"class": class_names[int(c)], "score": float(s), "box": [float(x) for x in b],
             "distance_m": None if not np.isfinite(d) else float(d)}
            for b, s, c, d in zip(boxes, det.scores, det.classes, dist)]
    if det.world_boxes is not None:
        for row, (cx, cy, cz, length, width, height, yaw) in zip(rows, det.world_boxes):
            row["box_3d"] = {"center": [float(cx), float(cy), float(cz)],
                             "size": [float(length), float(width), float(height)], "yaw": float(yaw)}
    return {"scenario": item["scenario"], "camera": item["camera_names"][v], "lighting": item["variant"],
            "source_views": item["camera_names"], "detections": rows}


def read_coco_results(path: str | Path, ds: Dataset, index: dict[ViewKey, tuple[str, int]],
                      split: str | None = None) -> dict[ViewKey, ViewDetections]:
    """A COCO results file -> detections per view (original pixels, detector class indices).

    One-line errors for an unreadable file, rows without COCO's fields, an image id that matches
    no image of ``split`` (or of the dataset), or a category that is no detectable class."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"results file {path} does not exist")
    try:
        rows = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"results file {path}: not JSON ({exc.__class__.__name__})") from None
    if not isinstance(rows, list):
        raise UserError(f"results file {path}: expected a list of detections (COCO results format)")
    by_id = {image_id: key for key, (s, image_id) in index.items() if split in (None, s)}
    class_of = {ds.info.class_id(name): k for k, name in enumerate(ds.info.detectable_classes)}
    found: dict[ViewKey, list] = {}
    for n, row in enumerate(rows):
        if not isinstance(row, dict) or not {"image_id", "category_id", "bbox", "score"} <= set(row):
            raise UserError(f"results file {path}: detection {n} lacks image_id, category_id, bbox or score")
        if row["image_id"] not in by_id:
            raise UserError(f"results file {path}: detection {n} has image_id {row['image_id']}, which is no image "
                            f"of {'split ' + split if split else 'the dataset'} (ids as in the COCO export)")
        if row["category_id"] not in class_of:
            raise UserError(f"results file {path}: detection {n} has category_id {row['category_id']}, not one of "
                            f"the detectable classes' ids {sorted(class_of)}")
        found.setdefault(by_id[row["image_id"]], []).append(row)
    out = {}
    for key in by_id.values():
        rs = found.get(key, [])
        out[key] = ViewDetections(np.array([box_from_coco(r["bbox"]) for r in rs]).reshape(-1, 4),
                                  np.array([float(r["score"]) for r in rs]),
                                  np.array([class_of[r["category_id"]] for r in rs], dtype=np.int64))
    return out


def score_results(results: dict[ViewKey, ViewDetections], dataset, match_ious: list[float]) -> MetricAccumulator:
    """The project's metrics for external detections on ``dataset``'s items (every scored view;
    detections converted to each item's encoded pixels)."""
    from pnyolo.evaluation.evaluate import scored_views

    acc = MetricAccumulator(match_ious, len(dataset.class_names), dataset.class_names)
    for k in range(len(dataset)):
        item = dataset[k]
        dets = []
        for v in range(len(item["camera_names"])):
            d = results.get((item["scenario"], item["camera_names"][v], item["variant"]))
            if d is None:
                dets.append(None)
                continue
            sx, sy = view_scale(item, v)
            s = np.array([sx, sy, sx, sy])
            dets.append(ViewDetections((d.boxes + 0.5) * s - 0.5, d.scores, d.classes))
        for v, det, gt in scored_views(item, dets):
            if det is None:
                raise UserError(f"results: no image of view {item['scenario']}/{item['camera_names'][v]} under "
                                f"lighting {item['variant']} (export and predict with the same --variant)")
            acc.add(det, gt)
    return acc
