"""The interface every model kind implements; the trainer, evaluation, inference, late fusion, ONNX
and the bench call only this (nerfstudio's ``Model``: outputs, a loss dict, decoding, one class per kind)::

    model = build_model(cfg, num_classes=2)               # the Model subclass registered as cfg.model.kind
    targets = model.targets(item)                         # its training targets (None: the loss reads item.gt)
    out = predict_item(model, item, "cpu", cfg.eval)      # model(**model.inputs(item, "cpu"), **model.eval_options(ev))
    loss, terms = model.loss(out, item, targets, "cpu")
    dets = model.decode(out, item, cfg.eval)              # ViewDetections per view of the item

A kind **must** provide ``forward`` (taking ``inputs``' keywords), ``loss`` and ``decode``. Everything
else has a default that works for every kind (no default crashes a caller):

==============================  =====================================================  =======================
part                            what it is for                                         default
==============================  =====================================================  =======================
``inputs(item, device)``        ``forward``'s keywords from an item                    images, K, camera_to_world, grid
``eval_options(ev)``            ``forward``'s keywords from the evaluation settings    none
``targets(item)``               the training targets ``loss`` gets                     None (``loss`` reads ``item.gt``)
``training_options(item, targets, train)``  a step's extra ``forward`` keywords        none, targets as given
``world_detections(out, item, ev, t)`` 3D detections per batch entry or view (``world_outputs``)  one-line error
``coverage_points(out, item)``  where it queried the world per road user               None (``coverage_text`` '')
``feature_bytes(item)``         bytes of one view's features another car would send    its encoder's maps, or None
``check_data(ds)``              one-line errors before training                        none
``config_key(parameter)``       the config key that builds a weight (load errors)      ``parameter_keys``, a part
``render_chunks(views, cells)`` passes one step takes (memory)                         1
``graph_inputs`` / ``export_graph`` / ``outputs_from_graph``  ONNX                     images, K, c2w; error; error
==============================  =====================================================  =======================

Capabilities are class attributes, read without building a model (``pnyolo.registry.model_class``):
``renders_rays`` (``forward`` takes ``ray_mask`` and ``drop_own_view``), ``reads_other_views``
(``forward`` takes ``own_view_only``), ``world_outputs``, ``tuned`` (the evaluation settings validation
chooses for it), and the words the bench's report uses: ``description``, ``own_view_text``,
``coverage_text`` (non-empty: ``forward`` takes ``return_samples`` and ``coverage_points`` answers),
``coverage_targets``. A kind without an image encoder leaves ``encoder`` None. The model keeps copies
of its own config section (``self.config``, its loss weights included) and ``data``; evaluation settings are passed in.
An analysis never gets the model: predictions hand it the model's ``Decoding`` (``decode``, ``world_detections``,
``coverage_points``, ``targets`` and what the kind gives), its outputs an opaque ``Outputs``.
docs/guide/detector.md ("Write your own model") walks through a new kind.
"""
from __future__ import annotations

import copy
import itertools
from dataclasses import dataclass, field
from typing import Callable, ClassVar, Protocol

import numpy as np
import torch
from torch import Tensor, nn

from dataset_spec.cli_support import UserError
from pnyolo.config import Config, EvalConfig, TrainConfig
from pnyolo.data.item import Item
from pnyolo.config.model import ModelConfig, field_names
from pnyolo.registry import model_class, register_model  # noqa: F401 - the kinds' decorator, re-exported
from pnyolo.decoding.detections import ViewDetections, WorldDetections

# (v, j, row) -> (P, 3) world points the model queries for road user j of view v (row in boxes_3d)
QueryPoints = Callable[[int, int, int], np.ndarray]
TUNABLE = ("nms_iou", "depth_gap", "depth_peaks")  # eval settings the bench's validation may choose for a kind


class Model(nn.Module):
    """One detector kind: item in, outputs, loss, detections per view."""

    kind = ""  # its registry name (set by register_model)
    description = ""  # one line for reports
    config_class: type[ModelConfig] = ModelConfig  # its ``model`` section (pnyolo.config.model)
    # Each cell is rendered on its own: a step may render a subset of them (``ray_mask``) and withhold
    # a ray's own view (``drop_own_view``); ``render_chunks`` says how many passes a step takes.
    renders_rays: ClassVar[bool] = False
    # A view's outputs read the other source views: the own-view-only ablation (``own_view_only``) applies.
    reads_other_views: ClassVar[bool] = True
    # It detects in 3D on the ground (``world_detections``): late fusion, detections moved under pose noise.
    world_outputs: ClassVar[bool] = False
    # Whether a perfect detector decoded as this kind decodes has a recall below 1 worth reporting (the encoding
    # ceiling of YOLO-grid targets: slots lost in a cell, amodal boxes suppressed by NMS; evaluate.encoding_ceiling)
    encoding_ceiling: ClassVar[bool] = False
    # Which of TUNABLE validation chooses for it (2D NMS, depth-gated NMS, depth peaks along a ray).
    tuned: ClassVar[tuple[str, ...]] = ("nms_iou",)
    own_view_text: ClassVar[str] = "each view read alone"  # how its own-view ablation works, for reports
    coverage_text: ClassVar[str] = ""  # where it queries the world for a road user ('': not measured)
    coverage_targets: ClassVar[dict[str, float]] = {}  # the coverage shares the bench holds it to
    # The config key that builds a weight, by the first part of the weight's name, where that part is not
    # a part of the kind's section of the same name (``config_key``).
    parameter_keys: ClassVar[dict[str, str]] = {}

    def __init__(self, cfg: Config, num_classes: int):
        super().__init__()
        # copies: what a caller later sets in its config (thresholds, statistics) never reaches the model
        self.config = copy.deepcopy(cfg.model)
        self.data_cfg = copy.deepcopy(cfg.data)
        self.num_classes = num_classes
        self.encoder: nn.Module | None = None  # its image encoder, if it has one (statistics, learning rates)

    def check_built(self) -> None:
        """What a built model of this kind must hold, refused in one line by ``build_model`` (a plugin kind's
        mistake named when it is built, not deep in training)."""

    def config_key(self, parameter: str) -> str:
        """The config key that builds the weight or buffer ``parameter`` (a checkpoint's mismatch names it):
        ``parameter_keys`` by its first part, else its section's part of that name, else ``model``."""
        first = parameter.split(".")[0]
        if first in self.parameter_keys:
            return self.parameter_keys[first]
        return f"model.{first}" if first in field_names(self.config) else "model"

    def inputs(self, item: Item, device) -> dict:
        """The keyword arguments of ``forward`` for an item (``pnyolo.data.dataset``)."""
        return {"images": item.images.to(device, non_blocking=True), "K": item.K.to(device, non_blocking=True),
                "camera_to_world": item.camera_to_world.to(device, non_blocking=True), "grid": item.grid}

    def rig_constants(self, item: Item) -> dict:
        """``forward``'s keywords that depend only on the item's cameras and image size, computed once for
        a rig that does not move (``Detector.for_rig``); the outputs with them are the outputs without."""
        return {}

    def eval_options(self, ev: EvalConfig) -> dict:
        """``forward``'s keywords that evaluation settings decide (outputs that depend on them)."""
        return {}

    def targets(self, item: Item) -> Tensor | None:
        """The training targets of ``item`` that ``loss`` gets (None: the loss reads ``item.gt``)."""
        return None

    def training_options(self, item: Item, targets, train: TrainConfig) -> tuple[dict, object]:
        """One training step's extra ``forward`` keywords and the targets the loss then sees."""
        return {}, targets

    def loss(self, out, item: Item, targets, device) -> tuple[Tensor, dict[str, float]]:
        """The training loss of ``out`` for ``item`` (``targets``: as ``training_options`` left them) and
        its terms' values."""
        raise NotImplementedError

    def decode(self, out, item: Item, ev: EvalConfig, conf_threshold: float | None = None) -> list[ViewDetections]:
        """Every view's detections (``conf_threshold`` overrides ``ev``'s); views not covered get none."""
        raise NotImplementedError

    def world_detections(self, out, item: Item, ev: EvalConfig, threshold: float) -> list[WorldDetections]:
        """3D detections of each batch entry of ``out`` of ``item`` (one per view with ``own_view_only``; a kind
        that detects in each view, one per view, a road user reported by every view that sees it)."""
        raise UserError(f"model.kind {self.kind} has no 3D detections")

    def coverage_points(self, out, item: Item) -> QueryPoints | None:
        """Where the model queried the world for each road user (``out`` from ``return_samples``),
        for ``pnyolo.evaluation.coverage``; None where it does not apply (``coverage_text`` empty)."""
        return None

    def coverage_stride(self) -> int:
        """Pixels of the finest map it reads (how near a queried point must project to count)."""
        return min(self.encoder.strides) if self.encoder is not None else 1

    @torch.no_grad()
    def feature_bytes(self, item: Item) -> int | None:
        """Bytes of one view's encoder feature maps (float32): what a car would send instead of its
        detections for a model that reads another car's features; None without an encoder."""
        if self.encoder is None:
            return None
        feats = self.encoder(item.images[:1].to(next(self.parameters()).device))
        return int(sum(f.numel() for f in feats) * 4)

    def check_data(self, ds) -> None:
        """One-line errors, before any work, for a dataset (MultiViewDataset) the model cannot use."""

    def render_chunks(self, num_views: int, cells: int) -> int:
        """Passes one training step over ``cells`` grid cells of ``num_views`` views takes (memory)."""
        return 1

    # ONNX (pnyolo.onnx.backend): the graph holds what runs on tensors; what chooses shapes stays in Python.
    def graph_inputs(self, item: Item) -> dict[str, Tensor]:
        """The exported graph's inputs for ``item``, by name (the example inputs of the export too)."""
        return {"images": item.images, "K": item.K, "camera_to_world": item.camera_to_world}

    def export_graph(self, item: Item, ev: EvalConfig) -> tuple[nn.Module, dict[str, dict[int, str]]]:
        """A module taking ``graph_inputs`` (in order) to a dict of output tensors, for ``item``'s
        grid and the evaluation settings ``ev``, and the dynamic axes of its inputs (empty: fixed)."""
        raise UserError(f"model.kind {self.kind} has no ONNX export")

    def graph_convention(self, ev: EvalConfig) -> dict:
        """How a caller decodes the graph's outputs (``pnyolo.onnx.convention``): {"outputs": {name:
        encoding}, "decoding": the steps after, "inputs": {name: meaning} of inputs beyond the views',
        and the constants both need, the evaluation settings' included}."""
        raise UserError(f"model.kind {self.kind} has no ONNX export")

    def outputs_from_graph(self, arrays: dict[str, Tensor], item: Item):
        """``forward``'s outputs for ``item`` rebuilt from the graph's output tensors (by name)."""
        raise UserError(f"model.kind {self.kind} has no ONNX export")


class Outputs(Protocol):
    """A kind's own outputs of one item (its forward's value: ``RayOutputs``, ``BevOutputs``, ...), opaque to
    everything but that kind's ``Decoding``."""


@dataclass(frozen=True, eq=False)
class Decoding:
    """What a trained model's outputs mean, without the model: the door ``pnyolo.engine.predict`` hands every
    analysis. It decodes outputs (2D and 3D detections, the points queried, the targets drawn in pictures) and
    says what the kind gives; it cannot run a forward pass or change a weight. ``world_outputs``: this model
    gives 3D detections; ``kind_world_outputs``: its kind can (a model trained without the state cannot)."""

    kind: str
    reads_other_views: bool
    world_outputs: bool
    kind_world_outputs: bool
    coverage_text: str
    _model: Model = field(repr=False)

    @classmethod
    def of(cls, model: Model) -> "Decoding":
        return cls(model.kind, model.reads_other_views, bool(model.world_outputs), bool(type(model).world_outputs),
                   model.coverage_text, model)

    def decode(self, out: Outputs, item: Item, ev: EvalConfig,
               conf_threshold: float | None = None) -> list[ViewDetections]:
        """``Model.decode``."""
        return self._model.decode(out, item, ev, conf_threshold)

    def world_detections(self, out: Outputs, item: Item, ev: EvalConfig, threshold: float) -> list[WorldDetections]:
        """``Model.world_detections``."""
        return self._model.world_detections(out, item, ev, threshold)

    def coverage_points(self, out: Outputs, item: Item) -> QueryPoints | None:
        """``Model.coverage_points``."""
        return self._model.coverage_points(out, item)

    def targets(self, item: Item) -> Tensor | None:
        """``Model.targets`` (what a picture of the item draws as the kind's targets)."""
        return self._model.targets(item)


def build_model(cfg: Config, num_classes: int) -> Model:
    model = model_class(cfg.model.kind)(cfg, num_classes)
    model.check_built()
    return model


def use_eval_stats(model: Model, cfg: Config, mode: str) -> None:
    """Switch a built detector's encoder batch-norm statistics outside training (``running`` |
    ``item``) and record it in its config, so reports and saved configs say what was used (a kind
    without an encoder has none to switch)."""
    if model.encoder is not None:
        model.encoder.set_eval_stats(mode)
    if hasattr(cfg.model, "encoder"):
        cfg.model.encoder.eval_stats = mode


def eval_stats(cfg: Config) -> str:
    """The batch-norm statistics ``cfg``'s encoder uses outside training ("running" for a kind without one)."""
    encoder = getattr(cfg.model, "encoder", None)
    return "running" if encoder is None else encoder.eval_stats


def model_device(model: nn.Module) -> torch.device:
    """Where ``model``'s weights are (the CPU for a model without any)."""
    for t in itertools.chain(model.parameters(), model.buffers()):
        return t.device
    return torch.device("cpu")


def to_device(value, device):
    """``value`` with every tensor in it (through dicts, lists and tuples) on ``device``."""
    if isinstance(value, Tensor):
        return value.to(device)
    if isinstance(value, dict):
        return {k: to_device(v, device) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(to_device(v, device) for v in value)
    return value


def rig_constants_on_device(model: Model, item: Item) -> dict:
    """``model.rig_constants(item)`` with every tensor on the model's device: a rig's constants live where the
    model does, whichever device a kind computed them on (by design, not by each kind's care)."""
    return to_device(model.rig_constants(item), model_device(model))


def predict_item(model: Model, item: Item, device=None, ev: EvalConfig | None = None, runner: nn.Module | None = None,
                 **options):
    """``model``'s outputs for one item (``device``: where its inputs go; None: the model's device);
    ``ev``: the evaluation settings its outputs depend on
    (``eval_options``; None: its defaults, as in training); ``runner``: what to call instead (a
    DistributedDataParallel wrapper of ``model``). ``options`` go to forward, those left at None or
    False unsaid (so a kind accepts only what it does): ``ray_mask`` and ``drop_own_view``
    (``renders_rays``), ``own_view_only`` (``reads_other_views``), ``return_samples`` (``coverage_text``)."""
    options = {k: v for k, v in options.items() if v is not None and v is not False}  # defaults stay unsaid
    rays = sorted({"ray_mask", "drop_own_view"} & set(options))
    if rays and not model.renders_rays:
        raise ValueError(f"model.kind {model.kind} renders no rays one by one: it cannot take {', '.join(rays)} "
                         "(it cannot drop a cell's own view, nor render a subset)")
    extra = model.eval_options(ev) if ev is not None else {}
    return (runner or model)(**model.inputs(item, model_device(model) if device is None else device), **extra, **options)
