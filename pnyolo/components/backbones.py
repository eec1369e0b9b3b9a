"""The image encoder ``model.encoder`` names, built for any model kind."""
from __future__ import annotations

from contextlib import contextmanager

from pnyolo.components.efficientnet import EfficientNetEncoder
from pnyolo.components.encoder import EncoderBase, ResNetEncoder
from pnyolo.config import Config


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


@contextmanager
def backbone_computed(model):
    """``model``'s encoder computes its backbone features inside the block, not reading a feature cache
    (a frame in use has none stored: timing and export see the real work); the cache is restored after."""
    encoder = getattr(model, "encoder", None)
    cache = getattr(encoder, "cache", None)
    if cache is not None:
        encoder.cache = None
    try:
        yield model
    finally:
        if cache is not None:
            encoder.cache = cache
