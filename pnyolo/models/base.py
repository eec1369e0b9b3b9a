"""The interface every model kind implements; the trainer, evaluation, inference, late fusion and
the bench call only this (nerfstudio's ``Model``: outputs, a loss dict, decoding, one class per kind)::

    model = build_model(cfg, num_classes=2)               # the Model subclass registered as cfg.model.kind
    out = predict_item(model, item, "cpu")                # model(**model.inputs(item, "cpu"))
    loss, terms = model.loss(out, item, item.targets, "cpu")
    dets = model.decode(out, item, cfg.eval)              # ViewDetections per view of the item

What a kind can do is declared as class attributes, read without building it (``model_class(kind)``):
``renders_rays``, ``reads_other_views``, ``world_outputs``. A new kind subclasses ``Model`` (or
``YoloGridModel`` for outputs on each view's YOLO grid) and registers with ``@register_model("name")``;
docs/guide/detector.md ("Write your own model") walks through one.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
from torch import Tensor, nn

from dataset_spec.cli_support import UserError
from pnyolo.config import Config, EvalConfig
from pnyolo.data.item import Item
from pnyolo.model_config import MODEL_CONFIGS, ModelConfig
from pnyolo.decoding.detections import ViewDetections, WorldDetections

# (v, j, row) -> (P, 3) world points the model queries for road user j of view v (row in boxes_3d)
QueryPoints = Callable[[int, int, int], np.ndarray]


class Model(nn.Module):
    """One detector kind: item in, outputs, loss, detections per view."""

    kind = ""  # its registry name (set by register_model)
    description = ""  # one line for reports
    config_class: type[ModelConfig] = ModelConfig  # its ``model`` section (pnyolo.model_config)
    # Each cell is rendered on its own: a step may render a subset of them (``ray_mask``) and withhold
    # a ray's own view (``drop_own_view``); ``render_chunks`` says how many passes a step takes.
    renders_rays = False
    # A view's outputs read the other source views: the own-view-only ablation (``own_view_only``) applies.
    reads_other_views = True
    # It detects in 3D on the ground (``world_detections``): late fusion, detections moved under pose noise.
    world_outputs = False

    def __init__(self, cfg: Config, num_classes: int):
        super().__init__()
        self.cfg, self.num_classes = cfg, num_classes

    def inputs(self, item: Item, device) -> dict:
        """The keyword arguments of ``forward`` for an item (``pnyolo.data.dataset``)."""
        return {"images": item.images.to(device), "K": item.K.to(device),
                "camera_to_world": item.camera_to_world.to(device), "grid": item.grid}

    def loss(self, out, item: Item, targets: Tensor, device) -> tuple[Tensor, dict[str, float]]:
        """The training loss of ``out`` for ``item`` (``targets``: the item's YOLO targets as the step
        rendered them) and its terms' values."""
        raise NotImplementedError

    def decode(self, out, item: Item, ev: EvalConfig, conf_threshold: float | None = None) -> list[ViewDetections]:
        """Every view's detections (``conf_threshold`` overrides ``ev``'s); views not covered get none."""
        raise NotImplementedError

    def world_detections(self, out, ev: EvalConfig, threshold: float) -> list[WorldDetections]:
        """3D detections of each batch entry of ``out`` (one per view with ``own_view_only``)."""
        raise UserError(f"model.kind {self.kind} has no 3D detections")

    def coverage_points(self, out, item: Item) -> QueryPoints | None:
        """Where the model queried the world for each road user (``out`` from ``return_samples``),
        for ``pnyolo.evaluation.coverage``; None where it does not apply."""
        return None

    def check_data(self, ds) -> None:
        """One-line errors, before any work, for a dataset (MultiViewDataset) the model cannot use."""

    def render_chunks(self, num_views: int, cells: int) -> int:
        """Passes one training step over ``cells`` grid cells of ``num_views`` views takes (memory)."""
        return 1

    # ONNX (pnyolo.deploy): the graph holds what runs on tensors; what chooses shapes stays in Python.
    def graph_inputs(self, item: Item) -> dict[str, Tensor]:
        """The exported graph's inputs for ``item``, by name (the example inputs of the export too)."""
        return {"images": item.images, "K": item.K, "camera_to_world": item.camera_to_world}

    def export_graph(self, item: Item) -> tuple[nn.Module, dict[str, dict[int, str]]]:
        """A module taking ``graph_inputs`` (in order) to a dict of output tensors, for ``item``'s
        grid, and the dynamic axes of its inputs (empty: the example's shapes are fixed)."""
        raise UserError(f"model.kind {self.kind} has no ONNX export")

    def outputs_from_graph(self, arrays: dict[str, Tensor], item: Item):
        """``forward``'s outputs for ``item`` rebuilt from the graph's output tensors (by name)."""
        raise UserError(f"model.kind {self.kind} has no ONNX export")


MODEL_REGISTRY: dict[str, type[Model]] = {}


def register_model(name: str):
    """Class decorator: ``name`` becomes a ``model.kind``, its ``model`` section ``cls.config_class``."""
    def deco(cls: type[Model]) -> type[Model]:
        if cls.renders_rays != cls.config_class.casts_rays:
            raise TypeError(f"{cls.__name__}.renders_rays and {cls.config_class.__name__}.casts_rays must agree")
        cls.kind = name
        MODEL_REGISTRY[name] = cls
        MODEL_CONFIGS.setdefault(name, cls.config_class)
        return cls
    return deco


def model_class(kind: str) -> type[Model]:
    """The registered class of ``kind`` (its capabilities), or a one-line error listing the kinds."""
    if kind not in MODEL_REGISTRY:
        raise UserError(f"config model.kind: {kind!r} ({' | '.join(sorted(MODEL_REGISTRY))})")
    return MODEL_REGISTRY[kind]


def build_model(cfg: Config, num_classes: int) -> Model:
    return model_class(cfg.model.kind)(cfg, num_classes)


def use_eval_stats(model: Model, cfg: Config, mode: str) -> None:
    """Switch a built detector's encoder batch-norm statistics outside training (``running`` |
    ``item``) and record it in its config, so reports and saved configs say what was used."""
    model.encoder.set_eval_stats(mode)
    cfg.model.encoder.eval_stats = mode


def predict_item(model: Model, item: Item, device, runner: nn.Module | None = None, **options):
    """``model``'s outputs for one item; ``runner``: what to call instead (a DistributedDataParallel
    wrapper of ``model``). ``options`` go to forward, those left at None or False unsaid (so a kind
    accepts only what it does): ``ray_mask`` and ``drop_own_view`` (``renders_rays``),
    ``own_view_only``, ``return_samples``."""
    options = {k: v for k, v in options.items() if v is not None and v is not False}  # defaults stay unsaid
    rays = sorted({"ray_mask", "drop_own_view"} & set(options))
    if rays and not model.renders_rays:
        raise ValueError(f"model.kind {model.kind} renders no rays one by one: it cannot take {', '.join(rays)} "
                         "(it cannot drop a cell's own view, nor render a subset)")
    return (runner or model)(**model.inputs(item, device), **options)
