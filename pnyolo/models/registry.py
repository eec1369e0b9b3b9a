"""The model registry and what every detector shares: building its encoder, running it on an item.

Every model maps an item's source views to per-view YOLO outputs on each view's grid::

    model = build_model(cfg, num_classes=2)            # cfg.model.kind picks the registry entry
    out = predict_item(model, item, "cpu")             # ViewOutputs, fields (V, S_h, S_w, A, ...)
    out.ray_confidence.shape                           # (V, S_h, S_w, A)

New kinds register with ``@register_model("name")`` (see ``pnyolo.models.pixelnerf_yolo``).
"""
from __future__ import annotations

from typing import Callable

from torch import nn

from dataset_spec.cli_support import UserError
from pnyolo.components.efficientnet import EfficientNetEncoder
from pnyolo.components.encoder import EncoderBase, ResNetEncoder
from pnyolo.components.renderer import RayOutputs
from pnyolo.config import Config

MODEL_REGISTRY: dict[str, Callable[[Config, int], nn.Module]] = {}

ViewOutputs = RayOutputs  # fields shaped (V, S_h, S_w, A, ...)


def register_model(name: str):
    def deco(fn):
        MODEL_REGISTRY[name] = fn
        return fn
    return deco


def build_model(cfg: Config, num_classes: int) -> nn.Module:
    if cfg.model.kind not in MODEL_REGISTRY:
        raise UserError(f"config model.kind: {cfg.model.kind!r} ({' | '.join(sorted(MODEL_REGISTRY))})")
    return MODEL_REGISTRY[cfg.model.kind](cfg, num_classes)


def use_eval_stats(model: nn.Module, cfg: Config, mode: str) -> None:
    """Switch a built detector's encoder batch-norm statistics outside training (``running`` |
    ``item``) and record it in its config, so reports and saved configs say what was used."""
    model.encoder.set_eval_stats(mode)
    cfg.model.encoder.eval_stats = mode


def make_encoder(cfg: Config) -> EncoderBase:
    """The image encoder ``model.encoder`` names: a ResNet (weights from a local file) or
    EfficientNet-Lite0 (ImageNet weights from its registry package with ``pretrained``)."""
    e = cfg.model.encoder
    if e.backbone == "efficientnet_lite0":
        return EfficientNetEncoder(e.num_layers, pretrained=e.pretrained, weights=e.weights, freeze=e.freeze,
                                   frozen_batchnorm=e.norm == "frozen_batch", eval_stats=e.eval_stats,
                                   fpn_channels=e.fpn_channels, feature_cache=e.feature_cache)
    enc = ResNetEncoder(e.backbone, e.num_layers, freeze=e.freeze, frozen_batchnorm=e.norm == "frozen_batch",
                        eval_stats=e.eval_stats,
                        context_channels=e.context_channels, context_dilation=e.context_dilation)
    if e.weights:
        enc.load_weights(e.weights)
    return enc


def predict_item(model, item: dict, device, ray_mask=None, own_view_only: bool = False,
                 drop_own_view=None, return_samples: bool = False) -> ViewOutputs:
    """The model's outputs for one item's views (``ray_mask``: render only these cells and
    ``drop_own_view``: these cells without their own view's features, see
    ``pnyolo.engine.ray_selection``; ``own_view_only``: each view from its own image features alone,
    the other source views dropped, see ``PixelNeRFYolo.forward``; ``return_samples``: keep the
    rendered samples, for models that render rays). A ground-plane model (``world_grid``) gets
    the item's scored views, whose sight its grid covers, and returns ``BevOutputs``."""
    extra = {"return_samples": True} if return_samples else {}
    if getattr(model, "world_grid", False):  # a ground-plane grid over the views evaluation scores
        extra["scored"] = item["scored"]
    return model(item["images"].to(device), item["K"].to(device), item["camera_to_world"].to(device), item["grid"],
                 ray_mask=ray_mask, own_view_only=own_view_only, drop_own_view=drop_own_view, **extra)
