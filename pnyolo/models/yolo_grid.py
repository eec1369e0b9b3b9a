"""What the kinds with outputs on each view's YOLO grid share (pixelnerf-yolo, single-view): the
``RayOutputs`` they return (fields (V, S_h, S_w, A, ...)), YOLO targets built from each view's ground
truth, the YOLO loss with its per-sample and surface-depth terms where the outputs carry them,
decoding by threshold and NMS, and the encoding ceiling (what a perfect detector decoded this way finds)."""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from dataset_spec.cli_support import UserError
from pnyolo.components.losses import YoloLoss
from pnyolo.components.renderer import RayOutputs
from pnyolo.config import EvalConfig
from pnyolo.config.model import GridModelConfig
from pnyolo.data.item import Item
from pnyolo.data.targets import view_targets
from pnyolo.decoding.detections import ViewDetections, WorldDetections
from pnyolo.decoding.yolo import decode_with, item_cameras
from pnyolo.models.base import Model
from pnyolo.onnx.convention import PIXELS, YOLO_GRID_DECODING, YOLO_GRID_OUTPUTS

ViewOutputs = RayOutputs  # fields shaped (V, S_h, S_w, A, ...)


class YoloGridModel(Model):
    """A kind whose forward returns ``ViewOutputs`` on each view's grid with the anchors in ``self.anchors``."""

    anchors: Tensor
    estimates_depth = True  # False: ``depth`` is all NaN, and an exported graph leaves it out
    encoding_ceiling = True  # its targets decode back with a loss: cells, anchors and NMS
    parameter_keys = {"anchors": "model.head.anchors"}
    config_class = GridModelConfig  # its anchors and objectness prior (``model.head``)

    def check_built(self) -> None:
        """Targets, loss and decoding read the anchors: a kind registers them as a buffer in ``__init__``."""
        buffer = dict(self.named_buffers()).get("anchors")
        if buffer is None or buffer.ndim != 2 or buffer.shape[-1] != 2:
            raise UserError(f"model.kind {self.kind}: a kind that decodes a YOLO grid registers its anchors in "
                            "__init__: self.register_buffer('anchors', torch.tensor(cfg.model.head.anchors))")

    def targets(self, item: Item) -> Tensor:
        """(V, S_h, S_w, A, TARGET_CHANNELS) YOLO targets of every view (``pnyolo.data.targets``)."""
        return torch.stack([view_targets(gt, item.grid, self.anchors.cpu(), self.config.head.ignore_threshold,
                                         self.config.loss) for gt in item.gt])

    def loss(self, out: ViewOutputs, item: Item, targets: Tensor, device) -> tuple[Tensor, dict[str, float]]:
        """The YOLO loss (``model.loss``'s weights) of every view's outputs."""
        return YoloLoss(self.config.loss)(out.ray_confidence, out.box, out.class_logits, targets.to(device),
                                          self.anchors, out.depth)

    def export_graph(self, item: Item, ev: EvalConfig) -> tuple[nn.Module, dict[str, dict[int, str]]]:
        return _GridGraph(self, item.grid, self.eval_options(ev), self.estimates_depth), {}

    def graph_convention(self, ev: EvalConfig) -> dict:
        return {"outputs": YOLO_GRID_OUTPUTS, "decoding": YOLO_GRID_DECODING, "anchors": self.anchors.tolist(),
                "conf_threshold": ev.conf_threshold, "nms_iou": ev.nms_iou, "depth_gap": ev.depth_gap,
                "pixels": PIXELS}

    def outputs_from_graph(self, arrays: dict[str, Tensor], item: Item) -> ViewOutputs:
        return unflatten_outputs(arrays)

    def decode(self, out: ViewOutputs, item: Item, ev: EvalConfig,
               conf_threshold: float | None = None) -> list[ViewDetections]:
        return decode_with(out.first_peaks(ev.depth_peaks), self.anchors, item.grid, ev, conf_threshold,
                           item_cameras(item))

    def world_detections(self, out: ViewOutputs, item: Item, ev: EvalConfig, threshold: float) -> list[WorldDetections]:
        """Each view's detections as world boxes (its distance and 3D state; ``decode``), one entry per view: a road
        user every view that sees it reports (``decoding.world.pool_views`` merges them); a one-line error for a
        model whose outputs place none (no 3D state)."""
        views = self.decode(out, item, ev, threshold)
        if any(d.world_boxes is None and len(d.scores) for d in views):
            raise UserError(f"model.kind {self.kind}: these outputs carry no 3D state (a model trained with "
                            "model.loss.state 0 places no 3D box)")
        return [WorldDetections(d.world_boxes.reshape(-1, 7) if d.world_boxes is not None else np.zeros((0, 7)),
                                d.scores, d.classes) for d in views]


def flatten_outputs(out: ViewOutputs, prefix: str = "", with_depth: bool = True) -> dict[str, Tensor]:
    """The tensors of ``out`` by name (the peaks' under ``peaks.``), for an exported graph; without
    ``depth`` where ``with_depth`` is False (a kind with no distance estimate), without ``state`` where it has none."""
    flat = {prefix + "confidence": out.ray_confidence, prefix + "box": out.box, prefix + "class_logits": out.class_logits}
    if with_depth:
        flat[prefix + "depth"] = out.depth
    if out.state.shape[-1]:
        flat[prefix + "state"] = out.state
    if out.surface_depth is not None:
        flat[prefix + "surface_depth"] = out.surface_depth
    if out.peaks is not None:
        flat.update(flatten_outputs(out.peaks, prefix + "peaks."))
    return flat


def unflatten_outputs(flat: dict[str, Tensor], prefix: str = "") -> ViewOutputs:
    """``flatten_outputs``' inverse (a graph without ``depth``: NaN, as the kind's own forward gives)."""
    peaks = unflatten_outputs(flat, prefix + "peaks.") if prefix + "peaks.confidence" in flat else None
    conf = flat[prefix + "confidence"]
    depth = flat.get(prefix + "depth", torch.full_like(conf, float("nan")))
    return ViewOutputs(conf, flat[prefix + "box"], flat[prefix + "class_logits"], depth,
                       flat.get(prefix + "surface_depth"), peaks, state=flat.get(prefix + "state"))


class _GridGraph(nn.Module):
    """A YOLO-grid model on one grid with its evaluation options: (images, K, camera_to_world) -> its
    outputs by name."""

    def __init__(self, model: YoloGridModel, grid, options: dict, with_depth: bool):
        super().__init__()
        self.model, self.grid, self.options, self.with_depth = model, grid, options, with_depth

    def forward(self, images: Tensor, K: Tensor, camera_to_world: Tensor) -> dict[str, Tensor]:
        out = self.model(images, K, camera_to_world, self.grid, **self.options)
        return flatten_outputs(out, with_depth=self.with_depth)
