"""Detections in the formats other tools read, and results of other detectors scored with ours.

    index = image_index(dataset.ds, variant="all")      # (scenario, camera, variant, frame) -> (split, id, stem)
    rows = coco_results(item, dets, index, class_ids)           # COCO results: image_id, category_id, bbox, score
    results = read_coco_results("predictions.json", dataset.ds, index)    # COCO or Ultralytics -> {view key: ViewDetections}
    acc = score_results(results, dataset, match_ious)           # the same metrics as for a checkpoint

Image ids are those of the project's COCO export of the same dataset (``tools.exporters.coco.
coco_image_ids``, every scenario, the same ``--variant``), so ``pycocotools.COCOeval`` scores a
results file against that export directly. Boxes are in the original images' pixels: COCO's
``[x, y, w, h]`` with pixel (0, 0) covering [0, 1] x [0, 1].
"""
from __future__ import annotations

import math
import sys
from collections import Counter
from pathlib import Path

import numpy as np

from dataset_spec import Dataset
from dataset_spec.cli_support import UserError
from dataset_spec.dataset import read_json
from dataset_spec.names import excerpt
from pnyolo.data.item import Item
from pnyolo.evaluation.metrics import MetricAccumulator, ViewDetections
from tools.exporters.coco import ImageRef, box_from_coco, coco_bbox, coco_image_ids

# Detections a received results file may hold per image (COCO's evaluation keeps an image's top 100, the nuScenes
# devkit refuses more than 500 a sample): more is refused, so scoring a file stays linear in its images.
MAX_RESULTS_PER_VIEW = 1000

ViewKey = tuple[str, str, str, int]  # (scenario, camera, lighting variant, frame)


def image_index(ds: Dataset, variant: str | None = None) -> dict[ViewKey, ImageRef]:
    """(scenario, camera, variant, frame) -> (split, COCO image id, file stem), as the exports name them."""
    return coco_image_ids(ds, None, variant)


def to_original(boxes: np.ndarray, scale: tuple[float, float]) -> np.ndarray:
    """Boxes (N, 4) in an item's encoded pixels -> the original image's pixels (scale = encoded / original)."""
    sx, sy = scale
    s = np.array([sx, sy, sx, sy])
    return (np.asarray(boxes, dtype=np.float64).reshape(-1, 4) + 0.5) / s - 0.5


def view_scale(item: Item, v: int) -> tuple[float, float]:
    width, height = item.original_sizes[v]
    return item.grid.width / width, item.grid.height / height


def coco_results(item: Item, dets: list[ViewDetections], index: dict[ViewKey, ImageRef],
                 class_ids: list[int]) -> list[dict]:
    """COCO result rows of an item's scored views (``dets`` one per view, in encoded pixels)."""
    rows = []
    for v in item.scored:
        key = (item.scenario, item.camera_names[v], item.variant, item.frame)
        if key not in index:
            continue  # a lighting variant the index does not export (see --variant)
        image_id = index[key].id
        d = dets[v]
        for box, score, cls in zip(to_original(d.boxes, view_scale(item, v)), d.scores, d.classes):
            rows.append({"image_id": image_id, "category_id": int(class_ids[int(cls)]),
                         "bbox": [round(x, 3) for x in coco_bbox(box)], "score": round(float(score), 5)})
    return rows


def view_record(item: Item, v: int, det: ViewDetections, class_names: list[str]) -> dict:
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
    return {"scenario": item.scenario, "camera": item.camera_names[v], "lighting": item.variant, "frame": item.frame,
            "source_views": item.camera_names, "detections": rows}


RESULT_KEYS = ("image_id", "category_id", "bbox", "score")


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _check_row(path: Path, n: int, row) -> None:
    """One-line errors for a results row that is not a COCO/Ultralytics detection."""
    where = f"results file {path}: detection {n}"
    if not isinstance(row, dict) or not set(RESULT_KEYS) <= set(row):
        raise UserError(f"{where} lacks image_id, category_id, bbox or score")
    if isinstance(row["image_id"], bool) or not isinstance(row["image_id"], (int, str)):
        raise UserError(f"{where}: image_id {row['image_id']!r} is neither an integer id nor an image file stem")
    if isinstance(row["category_id"], bool) or not isinstance(row["category_id"], int):
        raise UserError(f"{where}: category_id {row['category_id']!r} is not an integer")
    bbox = row["bbox"]
    if not isinstance(bbox, list) or len(bbox) != 4 or not all(_number(v) for v in bbox):
        raise UserError(f"{where}: bbox {bbox!r} is not 4 finite numbers [x, y, w, h]")
    if bbox[2] < 0 or bbox[3] < 0:
        raise UserError(f"{where}: bbox {bbox!r} has a negative width or height")
    if not _number(row["score"]):
        raise UserError(f"{where}: score {row['score']!r} is not a finite number")


def _say_variants(rows: list[dict], by_id: dict, path) -> None:
    """One line on stderr when the results name images of fewer lighting variants than are scored (results made on
    an export of the first variant, scored with ``--variant all``): the others' images count with no detections."""
    named = {by_id[r["image_id"]][2] for r in rows if r["image_id"] in by_id}
    scored = {key[2] for key in by_id.values()}
    if rows and named and named < scored:
        print(f"pnyolo-eval: note: results file {path} names images of lighting variant(s) {', '.join(sorted(named))} "
              f"only; the {', '.join(sorted(scored - named))} images are scored with no detections (give the "
              f"--variant the results were made for)", file=sys.stderr)


def read_coco_results(path: str | Path, ds: Dataset, index: dict[ViewKey, ImageRef], split: str | None = None,
                      class_base: int | None = None) -> dict[ViewKey, ViewDetections]:
    """A results file -> detections per view (original pixels, detector class indices).

    Two layouts, told apart by the image ids: COCO results whose integer ids and category ids are
    those of this dataset's COCO export, or Ultralytics' ``predictions.json`` (``model.val(save_json=
    True)`` on the YOLO export), whose ids are image file stems and whose categories are class indices
    counted from ``class_base`` (None: 0 when a detection has category 0, else 1, as Ultralytics 8.1+
    writes). One-line errors for an unreadable file, a malformed row, an image that is not in ``split``
    (or the dataset), or a category that is no detectable class."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"results file {path} does not exist")
    rows = read_json(path, "results file")
    if not isinstance(rows, list):
        raise UserError(f"results file {path}: expected a list of detections (COCO results format)")
    for n, row in enumerate(rows):
        _check_row(path, n, row)
    per_image = Counter(str(r["image_id"]) for r in rows)
    crowded = max(per_image, key=per_image.get, default=None)
    if crowded is not None and per_image[crowded] > MAX_RESULTS_PER_VIEW:
        raise UserError(f"results file {path}: image {excerpt(crowded)} has {per_image[crowded]} detections, more than "
                        f"{MAX_RESULTS_PER_VIEW} (keep each image's best, as COCO's evaluation keeps its top 100)")
    by_stem = any(isinstance(r["image_id"], str) for r in rows)
    if by_stem and not all(isinstance(r["image_id"], str) for r in rows):
        raise UserError(f"results file {path}: image ids mix integers (COCO ids) and file stems (Ultralytics)")
    in_split = {key: ref for key, ref in index.items() if split in (None, ref.split)}
    by_id = {(ref.stem if by_stem else ref.id): key for key, ref in in_split.items()}
    detectable = ds.info.detectable_classes
    if by_stem:
        base = class_base if class_base is not None else (0 if any(r["category_id"] == 0 for r in rows) else 1)
        class_of = {base + k: k for k in range(len(detectable))}
        kind = f"Ultralytics predictions (class indices from {base})"
    else:
        class_of = {ds.info.class_id(name): k for k, name in enumerate(detectable)}
        kind = "the COCO export's category ids"
    _say_variants(rows, by_id, path)
    found: dict[ViewKey, list] = {}
    for n, row in enumerate(rows):
        if row["image_id"] not in by_id:
            others = {ref.stem if by_stem else ref.id: ref.split for ref in index.values()}
            elsewhere = f" (it is in split {others[row['image_id']]})" if row["image_id"] in others else ""
            lit = {ref.id: key[2] for key, ref in coco_image_ids(ds, None, "all").items()} if not by_stem else {}
            if not elsewhere and row["image_id"] in lit:  # an image of a lighting variant not scored
                elsewhere = f" (an image of lighting variant {lit[row['image_id']]}: give --variant all)"
            raise UserError(f"results file {path}: detection {n} has image_id {row['image_id']!r}, which is no image "
                            f"of {'split ' + split if split else 'the dataset'}{elsewhere} "
                            f"({'file stems' if by_stem else 'ids'} as in the {'YOLO' if by_stem else 'COCO'} export)")
        if row["category_id"] not in class_of:
            raise UserError(f"results file {path}: detection {n} has category_id {row['category_id']}, not one of "
                            f"{sorted(class_of)} ({kind})")
        found.setdefault(by_id[row["image_id"]], []).append(row)
    out = {}
    for key in by_id.values():
        rs = found.get(key, [])
        out[key] = ViewDetections(np.array([box_from_coco(r["bbox"]) for r in rs]).reshape(-1, 4),
                                  np.array([float(r["score"]) for r in rs]),
                                  np.array([class_of[r["category_id"]] for r in rs], dtype=np.int64))
    return out


def score_results(results: dict[ViewKey, ViewDetections], dataset, match_ious: list[float],
                  progress: bool = False) -> MetricAccumulator:
    """The project's metrics for external detections on ``dataset``'s items (every scored view;
    detections converted to each item's encoded pixels); ``progress``: a bar on stderr."""
    from tqdm import tqdm

    from pnyolo.evaluation.evaluate import scored_views

    acc = MetricAccumulator(match_ious, len(dataset.class_names), dataset.class_names)
    for k in tqdm(range(len(dataset)), desc="scoring", unit="item", disable=not progress, file=sys.stderr):
        item = dataset[k]
        dets = []
        for v in range(len(item.camera_names)):
            d = results.get((item.scenario, item.camera_names[v], item.variant, item.frame))
            if d is None:
                dets.append(None)
                continue
            sx, sy = view_scale(item, v)
            s = np.array([sx, sy, sx, sy])
            dets.append(ViewDetections((d.boxes + 0.5) * s - 0.5, d.scores, d.classes))
        for v, det, gt in scored_views(item, dets):
            if det is None:
                raise UserError(f"results: no image of view {item.scenario}/{item.camera_names[v]} under "
                                f"lighting {item.variant} (export and predict with the same --variant)")
            acc.add(det, gt, item.scenario)
    return acc


def results_dataset(root, split: str, views: list[int] | None, index: dict):
    """Items to score external detections on: every camera once in items of up to 3 (or the cameras
    ``views``), the images at their own size, only the lighting variants ``index`` (the COCO export's
    image ids) numbers."""
    from pnyolo.config import load_config
    from pnyolo.data.dataset import MultiViewDataset, open_dataset

    if views is None:
        data = open_dataset(root)
        cameras = [len(data.scenario(s).cameras) for s in data.split(split)]
        views_per_item = min([3, *cameras])  # a scene of fewer cameras is scored in smaller items
    else:
        views_per_item = len(views)
    cfg = load_config(None, ["data.image_scale=1.0", f"data.num_views={views_per_item}"])
    ds = MultiViewDataset(root, split, cfg, training=False, views=views, every_camera=views is None)
    exported = {(scenario, variant, frame) for scenario, _, variant, frame in index}
    ds.items = [it for it in ds.items if (it.scenario, it.variant, it.frame) in exported]
    if not ds.items:
        raise UserError(f"no image of split {split} under the exported lighting variants (see --variant)")
    return ds, cfg
