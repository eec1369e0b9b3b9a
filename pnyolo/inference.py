"""A small inference API.

Example::

    det = Detector.load("runs/cpu/best.pt")
    results = det.detect([rgb0, rgb1, rgb2], [cam0, cam1, cam2])     # CameraInfo or (K, camera_to_world)
    for d in results[0]:
        print(d.class_name, d.score, d.box, d.distance)              # box in the input image's pixels

A ground-plane (``bev``) checkpoint answers the same way, each detection also carrying its world
box; its 3D boxes are projected into every given view with the default label thresholds.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from dataset_spec.cli_support import UserError
from pnyolo.components.backbones import backbone_computed
from pnyolo.config.checks import check_work
from pnyolo.data.frame import camera_pose, frame_item
from pnyolo.engine.checkpoint import load_detector, read_checkpoint
from pnyolo.engine.predict import predict
from pnyolo.evaluation.predictions import to_original
from pnyolo.models import rig_constants_on_device


@dataclass
class Detection:
    box: np.ndarray  # [x0, y0, x1, y1] pixels of the input image
    class_index: int
    class_name: str
    score: float
    distance: float  # metres along the ray (confidence-weighted depth); NaN when the model has none
    box_3d: np.ndarray | None = None  # world [cx, cy, cz, length, width, height, yaw] (bev models)


class Detector:
    """``runner``: what computes the model's outputs for an item instead of torch (an
    ``pnyolo.onnx.backend.OnnxRunner``); decoding is the model's either way."""

    def __init__(self, model, cfg, class_names, device="cpu", runner=None):
        self.model, self.cfg, self.class_names, self.device = model.eval(), cfg, class_names, device
        self.runner = runner

    @classmethod
    def load(cls, path: str | Path, device: str = "cpu", backend: str = "torch", onnx: str | Path | None = None,
             threads: int | None = None) -> "Detector":
        """``backend`` "onnxruntime" runs ``onnx`` (a file pnyolo-export wrote from this checkpoint)."""
        if backend not in ("torch", "onnxruntime") or (backend == "onnxruntime") != (onnx is not None):
            raise UserError("backend: 'torch', or 'onnxruntime' with the ONNX file exported from this checkpoint")
        ckpt = read_checkpoint(path)
        model, cfg = load_detector(ckpt, path, list(ckpt["class_names"]), device)
        runner = None
        if onnx is not None:
            from pnyolo.onnx.backend import OnnxRunner

            runner = OnnxRunner(onnx, model, threads)
        return cls(model, cfg, list(ckpt["class_names"]), device, runner)

    def for_rig(self, cameras: list, width: int, height: int) -> "RigDetector":
        """This detector for a rig whose cameras do not move (parked cars, Wildtrack, MultiviewX): what
        depends only on the cameras (``Model.rig_constants``) computed once for images of ``width`` x
        ``height``, then ``detect(images)`` frame after frame, with the outputs ``detect`` gives."""
        return RigDetector(self, cameras, width, height)

    @torch.no_grad()
    def detect(self, images: list[np.ndarray], cameras: list, conf_threshold: float | None = None,
               nms_iou: float | None = None, depth_gap: float | None = None,
               _constants: dict | None = None) -> list[list[Detection]]:
        """images: (H, W, 3) uint8 RGB per view; cameras: CameraInfo or (K, camera_to_world) per view.
        Thresholds left None come from the checkpoint's ``eval`` config."""
        item, scales = frame_item(images, cameras, self.cfg.data, self.class_names)
        check_work(self.cfg, item.grid)  # the 3D points a view asks for, before the model runs
        ev = replace(self.cfg.eval, nms_iou=nms_iou or self.cfg.eval.nms_iou,
                     depth_gap=depth_gap or self.cfg.eval.depth_gap)
        with backbone_computed(self.model):  # a new frame never hits a feature cache: nothing written there
            preds = predict(self.model, [item], ev, device=self.device, runner=self.runner,
                            constants=(lambda _: _constants) if _constants else None)
        dets = preds.detections_at(0, ev, conf_threshold)
        results = []
        for d, scale in zip(dets, scales):
            boxes = to_original(d.boxes, scale)
            results.append([Detection(boxes[k], int(d.classes[k]), self.class_names[int(d.classes[k])],
                                      float(d.scores[k]), float(d.distances[k]),
                                      None if d.world_boxes is None else d.world_boxes[k])
                            for k in range(len(d.boxes))])
        return results


class RigDetector:
    """``Detector.for_rig``: a detector bound to cameras that do not move; frames whose cameras differ
    are refused in one line (a moving rig: ``Detector.detect``, which takes each frame's cameras)."""

    def __init__(self, detector: Detector, cameras: list, width: int, height: int):
        self.detector, self.size = detector, (width, height)
        self.cameras = [camera_pose(c) for c in cameras]
        blank = [np.zeros((height, width, 3), np.uint8)] * len(cameras)
        item, _ = frame_item(blank, cameras, detector.cfg.data, detector.class_names)
        self._cameras_in = cameras
        self.constants = rig_constants_on_device(detector.model, item)

    def detect(self, images: list[np.ndarray], cameras: list | None = None, **thresholds) -> list[list[Detection]]:
        """``Detector.detect`` for this rig's cameras (``cameras``, if given, must be the rig's)."""
        if cameras is not None and (len(cameras) != len(self.cameras) or not all(
                np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) for a, b in zip(map(camera_pose, cameras), self.cameras))):
            raise UserError("these cameras are not the rig's (they moved): use Detector.detect, or for_rig again")
        if any(im.shape[1::-1] != self.size for im in images):
            raise UserError(f"the rig was set up for {self.size[0]}x{self.size[1]} images: use for_rig again")
        return self.detector.detect(images, self._cameras_in, _constants=self.constants, **thresholds)


class RigConstants:
    """``Model.rig_constants`` of the last rig seen, computed again only when an item's cameras, size or
    scored views differ from the one before (frames of a parked rig share them)."""

    def __init__(self, model):
        self.model, self.key, self.value = model, None, {}

    def __call__(self, item) -> dict:
        key = (item.K, item.camera_to_world, item.grid, list(item.scored), item.grid_views, item.mirrored)
        if self.key is None or not (torch.equal(key[0], self.key[0]) and torch.equal(key[1], self.key[1])
                                    and key[2:] == self.key[2:]):
            self.key, self.value = key, rig_constants_on_device(self.model, item)
        return self.value
