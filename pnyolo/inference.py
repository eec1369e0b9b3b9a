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
from pnyolo.data.frame import frame_item
from pnyolo.engine.checkpoint import load_detector, read_checkpoint
from pnyolo.evaluation.predictions import to_original
from pnyolo.models import predict_item


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
    ``pnyolo.onnx_backend.OnnxRunner``); decoding is the model's either way."""

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
            from pnyolo.onnx_backend import OnnxRunner

            runner = OnnxRunner(onnx, model, threads)
        return cls(model, cfg, list(ckpt["class_names"]), device, runner)

    @torch.no_grad()
    def detect(self, images: list[np.ndarray], cameras: list, conf_threshold: float | None = None,
               nms_iou: float | None = None, depth_gap: float | None = None) -> list[list[Detection]]:
        """images: (H, W, 3) uint8 RGB per view; cameras: CameraInfo or (K, camera_to_world) per view.
        Thresholds left None come from the checkpoint's ``eval`` config."""
        item, scales = frame_item(images, cameras, self.cfg.data, self.class_names)
        ev = replace(self.cfg.eval, nms_iou=nms_iou or self.cfg.eval.nms_iou,
                     depth_gap=depth_gap or self.cfg.eval.depth_gap)
        with backbone_computed(self.model):  # a new frame never hits a feature cache: nothing written there
            out = self.runner(item) if self.runner else predict_item(self.model, item, self.device, ev)
        dets = self.model.decode(out, item, ev, conf_threshold)
        results = []
        for d, scale in zip(dets, scales):
            boxes = to_original(d.boxes, scale)
            results.append([Detection(boxes[k], int(d.classes[k]), self.class_names[int(d.classes[k])],
                                      float(d.scores[k]), float(d.distances[k]),
                                      None if d.world_boxes is None else d.world_boxes[k])
                            for k in range(len(d.boxes))])
        return results
