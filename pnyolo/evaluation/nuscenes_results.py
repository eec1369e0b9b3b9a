"""3D detections in nuScenes' submission format (``results_nusc.json``), written by ``pnyolo-predict`` and read
back by ``pnyolo-eval --results``, so a detector trained on the nuScenes export and ours are scored by the same
devkit call (sample tokens: ``dataset_spec.nuscenes_format``)::

    pool = WorldPool(preds.decoding, cfg.eval, ds); pool.add(out, item)  # a world-output model's boxes per sample
    doc = pool.document(class_names)                             # {"meta": ..., "results": {token: [box, ...]}}
    rows = result_rows(token, world_dets, class_names, offset)   # one sample's boxes, in its scene's global frame
    results = read_results("results_nusc.json", ds, split, class_names)   # (scenario, variant, frame) -> WorldDetections
    acc = score_world_results(results, dataset, match_ious)      # our metrics: every scored view, the devkit's 3D

A box: ``sample_token``, ``translation`` (x, y, z m in the export's global frame: our world moved by its
scenario's ``global_offset``), ``size`` (width, length, height m), ``rotation``
(w, x, y, z), ``velocity`` (vx, vy m/s; 0 where the model estimates none), ``detection_name`` (the class),
``detection_score`` in [0, 1], ``attribute_name`` (a nuScenes attribute or ""). Reading checks every field and
names the first that is wrong in one line.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from dataset_spec import Dataset
from dataset_spec.cli_support import UserError
from dataset_spec.dataset import read_json
from dataset_spec.names import JoinedNames, excerpt
from dataset_spec.nuscenes_format import (ATTRIBUTES, GlobalFrames, dataset_class_of, quaternion_yaw, sample_token,
                                          yaw_quaternion)
from pnyolo.decoding.detections import WorldDetections
from pnyolo.models.base import Decoding
from pnyolo.evaluation.metrics import MetricAccumulator

SampleKey = tuple[str, str, int]  # (scenario, lighting variant, frame)
MAX_BOXES_PER_SAMPLE = 500  # the devkit refuses more (DetectionEval: "only <= 500 boxes per sample allowed")


def result_rows(token: str, dets: WorldDetections, class_names: list[str], offset=(0.0, 0.0, 0.0)) -> list[dict]:
    """One sample's detections as nuScenes result boxes, their world centres moved by ``offset`` (the scenario's
    ``global_offset``: into its export's global frame)."""
    rows = []
    for k in range(len(dets)):
        cx, cy, cz, length, width, height, yaw = (float(v) for v in dets.boxes[k])
        v = (0.0, 0.0) if dets.velocities is None else tuple(float(x) for x in dets.velocities[k])
        rows.append({"sample_token": token, "translation": [cx + float(offset[0]), cy + float(offset[1]),
                                                            cz + float(offset[2])], "size": [width, length, height],
                     "rotation": yaw_quaternion(yaw), "velocity": list(v),
                     "detection_name": class_names[int(dets.classes[k])], "detection_score": float(dets.scores[k]),
                     "attribute_name": "" if dets.attributes is None else dets.attributes[k]})
    return rows


class WorldPool:
    """A world-output model's detections pooled per sample over the items that show it (several items of one
    sample's cameras, each with its own grid), merged by ``eval.centre_nms_m``, each sequence's then given a
    velocity and an attribute from their tracks (``pnyolo.decoding.motion``); ``active`` only for such models;
    ``ds``: the dataset they are of (its scenarios' global frames and frame rates)."""

    def __init__(self, decoding: Decoding, ev, ds):
        self.decoding, self.ev, self.samples, self.ds = decoding, ev, {}, ds
        self.frames = GlobalFrames(ds)
        self.active = decoding.world_outputs

    def add(self, out, item) -> None:
        if self.active:
            key = (item.scenario, item.variant, item.frame)
            self.samples.setdefault(key, []).extend(self.decoding.world_detections(out, item, self.ev,
                                                                                  self.ev.conf_threshold))

    def document(self, class_names: list[str]) -> dict:
        from pnyolo.decoding.world import pool_views
        from pnyolo.decoding.motion import with_motion

        sequences: dict[tuple[str, str], dict[int, WorldDetections]] = {}
        for (scenario, variant, frame), parts in self.samples.items():
            merged = pool_views(parts, self.ev.centre_nms_m)
            sequences.setdefault((scenario, variant), {})[frame] = merged
        rows = {}
        for (scenario, variant), by_frame in sequences.items():
            order = sorted(by_frame)
            moved = with_motion([by_frame[f] for f in order], self.ds.scenario(scenario).fps, class_names)
            for frame, dets in zip(order, moved):
                token = sample_token(scenario, variant, frame)
                rows[token] = result_rows(token, dets, class_names, self.frames(scenario))
        return results_document(rows)


def results_document(rows: dict[str, list[dict]]) -> dict:
    return {"meta": {"use_camera": True, "use_lidar": False, "use_radar": False, "use_map": False,
                     "use_external": False}, "results": rows}


def _samples(ds: Dataset, split: str) -> dict[str, SampleKey]:
    """Every sample token of ``split`` (each scenario's frames under each lighting) -> its key."""
    scenes = JoinedNames("nuScenes scene")  # two (scenario, variant) pairs of one name would share their samples
    return {sample_token(s, v.name, f): (s, v.name, f) for s in ds.split(split) for v in ds.scenario(s).lighting
            if scenes(s, v.name) for f in ds.frames(s)}


def _numbers(value, n: int, where: str) -> list[float]:
    if not (isinstance(value, list) and len(value) == n and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                                and math.isfinite(x) for x in value)):
        raise UserError(f"{where}: expected {n} finite numbers, got {excerpt(value)}")
    return [float(x) for x in value]


def _box(box, token: str, where: str, class_names: list[str]) -> tuple:
    if not isinstance(box, dict):
        raise UserError(f"{where}: expected a box (a mapping), got {excerpt(box)}")
    if box.get("sample_token") != token:
        raise UserError(f"{where}.sample_token: {excerpt(box.get('sample_token'))} is not its sample {token}")
    x, y, z = _numbers(box.get("translation"), 3, f"{where}.translation")
    w, length, h = _numbers(box.get("size"), 3, f"{where}.size")
    if min(w, length, h) <= 0:
        raise UserError(f"{where}.size: sizes must be > 0, got {[w, length, h]}")
    q = _numbers(box.get("rotation"), 4, f"{where}.rotation")
    if not 0.5 < math.sqrt(sum(c * c for c in q)) < 2:
        raise UserError(f"{where}.rotation: not a unit quaternion (w, x, y, z), got {q}")
    for key, none in (("velocity", "[0, 0]"), ("attribute_name", '""')):  # the devkit's DetectionBox reads both
        if key not in box:
            raise UserError(f"{where}: no {key} (nuScenes' results format needs it; {none} where none is estimated)")
    v = _numbers(box["velocity"], 2, f"{where}.velocity")
    name, score = box.get("detection_name"), box.get("detection_score")
    name = name if name in class_names else dataset_class_of(name) if isinstance(name, str) else None
    if name not in class_names:  # bus and truck are the dataset's car, as the export wrote them
        raise UserError(f"{where}.detection_name: {excerpt(box.get('detection_name'))} is not a class of the dataset "
                        f"({class_names}) nor one its nuScenes export writes")
    if isinstance(score, bool) or not isinstance(score, (int, float)) or not 0 <= score <= 1:
        raise UserError(f"{where}.detection_score: a score in [0, 1], got {excerpt(score)}")
    attribute = box["attribute_name"]
    if attribute not in ("", *ATTRIBUTES):
        raise UserError(f"{where}.attribute_name: {excerpt(attribute)} is not a nuScenes attribute")
    return [x, y, z, length, w, h, quaternion_yaw(q)], float(score), class_names.index(name), v, attribute


def is_nuscenes_results(path: str | Path) -> bool:
    """Whether a .json results file is nuScenes' (a mapping with "results") rather than COCO's (a list)."""
    try:
        with open(path, encoding="utf-8") as f:
            head = f.read(4096).lstrip()
    except OSError as exc:
        raise UserError(f"results file {path}: not readable ({exc.__class__.__name__})") from None
    return head.startswith("{")


def read_results(path: str | Path, ds: Dataset, split: str, class_names: list[str]) -> dict[SampleKey, WorldDetections]:
    """A nuScenes results file's boxes by sample of ``split`` (every field checked; one line for the first wrong)."""
    doc = read_json(path, "results file")
    if not isinstance(doc, dict) or not isinstance(doc.get("results"), dict) or not isinstance(doc.get("meta"), dict):
        has = f"its keys {excerpt(sorted(doc))}" if isinstance(doc, dict) else "not a mapping"
        raise UserError(f"results file {path} ({has}; the devkit reads both meta and results): expected nuScenes' "
                        "{\"meta\": ..., \"results\": {sample_token: [boxes]}}")
    known, out, others = _samples(ds, split), {}, {name: _samples(ds, name) for name in ("train", "val", "test")}
    frames = GlobalFrames(ds)
    for token, boxes in doc["results"].items():
        where = f"results[{excerpt(token)}]"
        if token not in known:
            other = next((name for name in ("train", "val", "test") if name != split and token in others[name]), None)
            raise UserError(f"{where}: a sample of split {other}, not {split} (--split)" if other else
                            f"{where}: not a sample of {ds.root} (the tokens of its nuScenes export)")
        if not isinstance(boxes, list):
            raise UserError(f"{where}: expected a list of boxes, got {excerpt(boxes)}")
        if len(boxes) > MAX_BOXES_PER_SAMPLE:
            raise UserError(f"{where}: {len(boxes)} boxes, more than the devkit's {MAX_BOXES_PER_SAMPLE} a sample")
        rows = [_box(b, token, f"{where}[{i}]", class_names) for i, b in enumerate(boxes)]
        world = np.array([r[0] for r in rows], dtype=np.float64).reshape(-1, 7)
        world[:, :3] -= frames(known[token][0])  # from the export's global frame
        out[known[token]] = WorldDetections(world,
                                            np.array([r[1] for r in rows], dtype=np.float64),
                                            np.array([r[2] for r in rows], dtype=np.int64),
                                            np.array([r[3] for r in rows], dtype=np.float64).reshape(-1, 2),
                                            [r[4] for r in rows])
    return out


def score_world_results(results: dict[SampleKey, WorldDetections], dataset, match_ious: list[float],
                        progress: bool = False) -> MetricAccumulator:
    """The project's metrics for 3D results: each sample's boxes put into every scored view as a model's are
    (``project_into_views``), a sample the file leaves out holding no detections."""
    from tqdm import tqdm

    from pnyolo.decoding.world import project_into_views
    from pnyolo.evaluation.evaluate import scored_views

    acc = MetricAccumulator(match_ious, len(dataset.class_names), dataset.class_names)
    for k in tqdm(range(len(dataset)), desc="scoring", unit="item", disable=not progress, file=sys.stderr):
        item = dataset[k]
        dets = results.get((item.scenario, item.variant, item.frame), WorldDetections.empty())
        for _, det, gt in scored_views(item, project_into_views(dets, item, item.scored)):
            acc.add(det, gt, item.scenario)
    return acc
