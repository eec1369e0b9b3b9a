"""COCO detection JSON, one file per split, amodal as the amodal datasets (COCOA, KINS) write it.

Layout: ``images/<split>/<stem>.png`` and ``annotations/instances_<split>.json``.

* ``bbox``: the amodal box clipped to the image, ``[x, y, w, h]`` in COCO pixel coordinates,
  where pixel (0, 0) covers [0, 1] x [0, 1] (ours has its centre at (0, 0): x_coco = x + 0.5).
* ``segmentation``: the *amodal* mask, the pixels of the road user's whole silhouette in the image,
  hidden parts included; ``area``: its pixels. So a fully hidden car has its real size, and COCO's
  small / medium / large buckets sort it as it would be seen. Masks are uncompressed RLE
  (``{"size": [H, W], "counts": [...]}``, column-major, runs starting with background).
* ``visible_segmentation``: the *visible* pixels (the instance segmentation, empty when fully
  hidden); ``visible_area``: their count.
* ``iscrowd: 1`` marks a road user the label thresholds left out of the ground truth (too
  truncated, too far, too small): COCOeval ignores detections on it, as KITTI's DontCare does.
* extra per-annotation fields: ``instance_id``, ``visible_fraction``, ``in_frame_fraction``,
  ``occlusion_level``, ``distance``. ``category_id`` is the dataset's class id.
* sequences (CocoVID, as MMTracking reads it): ``videos`` ({id, name, fps, width, height}: one camera of
  a sequence under one lighting), images add ``video_id`` and ``frame_id`` (from 0), annotations
  ``video_id``; ``instance_id`` is the track id. An export of one-frame scenarios has none of these.

Usage::

    folder = export_coco(ds, "out/exports/coco")
    mask = rle_decode(annotation["segmentation"])        # (H, W) bool
"""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from dataset_spec import Dataset, LabelThresholds
from dataset_spec.atomic import atomic_write_json
from dataset_spec.dataset import read_json
from dataset_spec.names import below

from tools.projection import amodal_mask, moved_meshes, scenario_meshes

from .common import UNSPLIT, copy_file, export_stems, export_views, scenario_splits, sequence_names


def rle_encode(mask: np.ndarray) -> dict:
    """(H, W) bool mask -> uncompressed COCO RLE ``{"size": [H, W], "counts": [int, ...]}``."""
    mask = np.asarray(mask, dtype=bool)
    flat = mask.ravel(order="F").astype(np.int8)
    change = np.flatnonzero(np.diff(flat)) + 1
    bounds = np.concatenate([[0], change, [flat.size]])
    counts = np.diff(bounds).tolist()
    if flat.size and flat[0]:
        counts = [0] + counts  # runs start with background
    return {"size": [int(mask.shape[0]), int(mask.shape[1])], "counts": [int(c) for c in counts]}


def rle_decode(rle: dict) -> np.ndarray:
    """Inverse of ``rle_encode`` -> (H, W) bool."""
    h, w = rle["size"]
    counts = np.asarray(rle["counts"], dtype=np.int64)
    if counts.sum() != h * w:
        raise ValueError(f"RLE counts sum to {counts.sum()}, expected {h * w}")
    values = np.arange(len(counts)) % 2 == 1
    return np.repeat(values, counts).reshape((h, w), order="F")


def coco_bbox(box) -> list[float]:
    """Our ``[x0, y0, x1, y1]`` -> COCO ``[x, y, w, h]``."""
    x0, y0, x1, y1 = (float(v) for v in box)
    return [x0 + 0.5, y0 + 0.5, x1 - x0, y1 - y0]


def box_from_coco(bbox) -> np.ndarray:
    """COCO ``[x, y, w, h]`` -> our ``[x0, y0, x1, y1]``."""
    x, y, w, h = (float(v) for v in bbox)
    return np.array([x - 0.5, y - 0.5, x - 0.5 + w, y - 0.5 + h])


class ImageRef(NamedTuple):
    """An exported image: its split, its COCO id and its file stem (in every export format)."""

    split: str
    id: int
    stem: str


def coco_image_ids(ds: Dataset, scenarios: list[str] | None = None, variant: str | None = None
                   ) -> dict[tuple[str, str, str], ImageRef]:
    """Every exported view: (scenario, camera, lighting variant, frame) -> ``ImageRef``. An id names one image
    whichever split's file holds it and whichever lighting variants the export holds: the images are counted from 1
    in export order over every variant, and an export of fewer variants keeps their ids (so results made on an
    export of the first variant, scored with ``--variant all``, still name the images they were made on). Detection
    results for the export (for COCOeval: ``pnyolo-predict``) and results read back (``pnyolo-eval --results``) use
    these ids; Ultralytics' predictions name images by ``stem``."""
    names = scenarios if scenarios is not None else ds.scenario_names()
    every = {key: n for n, key in enumerate(export_stems(ds, names, "all"), start=1)}  # export_views' order, no labels
    split_of = scenario_splits(ds)
    return {(scenario, camera, var, frame): ImageRef(split_of.get(scenario, UNSPLIT), every[scenario, camera, frame, var],
                                                     stem)
            for (scenario, camera, frame, var), stem in export_stems(ds, names, variant).items()}


def video_ids(ds: Dataset, scenarios: list[str] | None = None, variant: str | None = None
              ) -> dict[tuple[str, str, str], dict]:
    """CocoVID's videos of an export that holds a sequence: (scenario, camera, lighting variant) -> ``{"id",
    "name", "fps", "width", "height"}``, ids from 1 in export order; empty when every scenario is one frame
    (the export is then plain COCO, as before sequences)."""
    names = scenarios if scenarios is not None else ds.scenario_names()
    if all(ds.scenario(n).frames == 1 for n in names):
        return {}
    out, named = {}, sequence_names(ds, names, variant)
    for view in export_views(ds, names, None, variant):
        key = (view.scenario, view.camera.name, view.variant)
        if key not in out:
            out[key] = {"id": len(out) + 1, "name": named[key],
                        "fps": ds.scenario(view.scenario).fps or 1, "width": view.camera.width,
                        "height": view.camera.height}
    return out


def export_coco(ds: Dataset, out_dir: str | Path, scenarios: list[str] | None = None,
                thresholds: LabelThresholds | None = None, variant: str | None = None) -> Path:
    """Write images and one ``instances_<split>.json`` per split under ``out_dir``; returns ``out_dir``."""
    out = Path(out_dir)
    detectable = ds.info.detectable_classes
    categories = [{"id": ds.info.class_id(n), "name": n, "supercategory": "road_user"} for n in detectable]
    files: dict[str, dict] = {}
    instance_cache: dict[tuple[str, str], np.ndarray] = {}
    mesh_cache: dict[str, dict] = {}
    image_ids = coco_image_ids(ds, scenarios, variant)
    videos = video_ids(ds, scenarios, variant)
    for view in export_views(ds, scenarios, thresholds, variant):
        doc = files.setdefault(view.split, {"info": {"description": f"{ds.info.name} ({view.split})",
                                                     "spec_version": ds.info.spec_version},
                                            "images": [], "annotations": [], "categories": categories})
        copy_file(view.image_path, below(out, "images", view.split, f"{view.stem}.png"))
        image_id = image_ids[(view.scenario, view.camera.name, view.variant, view.frame)][1]
        doc["images"].append({"id": image_id, "file_name": f"{view.stem}.png", "width": view.camera.width,
                              "height": view.camera.height, "scenario": view.scenario, "camera": view.camera.name,
                              "lighting": view.variant})
        video = {}
        if videos:  # CocoVID: a video is one camera of a sequence under one lighting; frame_id from 0
            video = {"video_id": videos[(view.scenario, view.camera.name, view.variant)]["id"]}
            doc["images"][-1].update(video, frame_id=view.frame)
            doc.setdefault("videos", [])
            if video["video_id"] not in {v["id"] for v in doc["videos"]}:
                doc["videos"].append(videos[(view.scenario, view.camera.name, view.variant)])
        if not ds.info.has("instance"):  # camera data: boxes only, no masks to draw them from
            doc["annotations"] += [{
                "id": len(doc["annotations"]) + k + 1, "image_id": image_id, "category_id": ds.info.class_id(o.cls),
                "bbox": coco_bbox(o.box), "area": float(np.prod(coco_bbox(o.box)[2:])), "iscrowd": crowd,
                "instance_id": o.instance_id, "visible_fraction": None, "in_frame_fraction": o.in_frame_fraction,
                "occlusion_level": o.occlusion_level, "distance": o.distance, **video}
                for k, (crowd, o) in enumerate([(0, o) for o in view.labels] + [(1, o) for o in view.ignored])
                if o.cls in detectable]
            continue
        key = (view.scenario, view.camera.name, view.frame)
        if key not in instance_cache:
            instance_cache = {key: ds.read_instance(*key)}  # variants of a view share it
        if (view.scenario, view.frame) not in mesh_cache:
            first = mesh_cache.get((view.scenario, 0)) or scenario_meshes(ds, ds.scenario(view.scenario))
            mesh_cache = {(view.scenario, 0): first,
                          (view.scenario, view.frame): moved_meshes(ds, view.scenario, first, view.frame)}
        instance, meshes = instance_cache[key], mesh_cache[(view.scenario, view.frame)]
        for crowd, labels in ((0, view.labels), (1, view.ignored)):
            for o in labels:
                if o.cls not in detectable:
                    continue
                amodal, visible = amodal_mask(view.camera, meshes[o.instance_id]), instance == o.instance_id
                doc["annotations"].append({
                    "id": len(doc["annotations"]) + 1, "image_id": image_id, "category_id": ds.info.class_id(o.cls),
                    "bbox": coco_bbox(o.box), "area": int(amodal.sum()), "iscrowd": crowd,
                    "segmentation": rle_encode(amodal), "visible_segmentation": rle_encode(visible),
                    "visible_area": int(visible.sum()), "instance_id": o.instance_id,
                    "visible_fraction": o.visible_fraction, "in_frame_fraction": o.in_frame_fraction,
                    "occlusion_level": o.occlusion_level, "distance": o.distance, **video})
    for split, doc in files.items():
        atomic_write_json(out / "annotations" / f"instances_{split}.json", doc)
    return out


def read_coco(path: str | Path) -> dict:
    """Load an exported COCO file (plain JSON; pycocotools' ``COCO(path)`` reads it too)."""
    return read_json(path, "COCO file")
