"""ResNet-18/34 image encoder in plain torch (no torchvision), pixelNeRF style.

Parameter names match torchvision's ``resnet18``/``resnet34`` (``conv1``, ``bn1``,
``layer1.0.conv1`` ... ``layer4.1.downsample.0``) so a user's local state dict loads::

    enc = ResNetEncoder("resnet34", num_layers=4)
    enc.load_weights("resnet34-b627a593.pth")      # fc.* keys are ignored
    feats = enc(images)                              # list of (V, C_l, H_l, W_l)
    enc.latent_size                                  # 512 for num_layers=4 (64+64+128+256)

pixelNeRF takes the conv1 output (stride 2) and layer1..layer{num_layers-1}, upsamples them to
stride 2 and concatenates. Here each layer is bilinearly indexed at the projected point instead
(``index_features``): the same values without materialising the upsampled maps, which keeps full
HD inputs inside the memory budget. Feature j of a map of stride s is centred on image pixel s * j
(the padding of every ResNet convolution and of the max pool keeps centres there), so a pixel u
is read at feature coordinate u / s on every map (``enc.strides``).
"""
from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from dataset_spec.cli_support import UserError
from pnyolo.config.checks import EVAL_STATS

_BLOCKS = {"resnet18": (2, 2, 2, 2), "resnet34": (3, 4, 6, 3)}
_CHANNELS = (64, 128, 256, 512)


class BatchNorm2d(nn.BatchNorm2d):
    """``nn.BatchNorm2d`` (same parameters and buffers) that can also normalise with the batch's
    own statistics when not training (``item_stats``), leaving the running statistics untouched.
    A batch here is one item's views: training normalises every step with them, so evaluating the
    same way removes the gap between those statistics and the running averages over all scenes
    and lightings."""

    item_stats = False

    def forward(self, x: Tensor) -> Tensor:
        if self.training or not self.item_stats:
            return super().forward(x)
        return F.batch_norm(x, None, None, self.weight, self.bias, True, 0.0, self.eps)


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(self, inplanes: int, planes: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 3, stride, 1, bias=False)
        self.bn1 = BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(planes, planes, 3, 1, 1, bias=False)
        self.bn2 = BatchNorm2d(planes)
        self.downsample = None
        if stride != 1 or inplanes != planes:
            self.downsample = nn.Sequential(nn.Conv2d(inplanes, planes, 1, stride, bias=False), BatchNorm2d(planes))

    def forward(self, x: Tensor) -> Tensor:  # (V, inplanes, H, W) -> (V, planes, H / stride, W / stride)
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


def read_state_dict(path: Path):
    """The tensors saved in an encoder weights file (one-line errors for a missing or unreadable one)."""
    if not path.is_file():
        raise UserError(f"encoder weights {path} do not exist")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is a user error
        raise UserError(f"encoder weights {path}: not a readable torch state dict ({exc.__class__.__name__})") from None


class EncoderBase(nn.Module):
    """What every image encoder shares: ``channels``, ``strides`` (image pixels per feature of each
    map, feature j centred on pixel stride * j) and ``latent_size`` set by the subclass; freezing;
    and the batch-norm statistics used outside training."""

    channels: list[int]
    strides: list[int]
    latent_size: int
    frozen = frozen_batchnorm = False

    def freeze_backbone(self, freeze: bool, frozen_batchnorm: bool) -> None:
        """``freeze``: the parameters built so far get no gradient (and batch norm keeps its running
        statistics); ``frozen_batchnorm``: batch norm uses its running statistics, even in training."""
        self.frozen = freeze
        self.frozen_batchnorm = frozen_batchnorm or freeze
        if freeze:
            for p in self.parameters():
                p.requires_grad_(False)

    def backbone_parameters(self) -> list:
        """The parameters pretrained weights are for (``train.encoder_lr_scale`` applies to them)."""
        return [p for n, p in self.named_parameters() if n.split(".")[0] in self.backbone_modules]

    backbone_modules: tuple[str, ...] = ()

    def set_eval_stats(self, mode: str) -> None:
        """Batch norm statistics outside training: ``running`` (PyTorch's default: averages kept
        during training) or ``item`` (the statistics of the views encoded together, as in
        training). No effect with frozen batch norm, which always uses the running ones."""
        if mode not in EVAL_STATS:
            raise ValueError(f"unknown eval_stats {mode!r} ({' | '.join(EVAL_STATS)})")
        self.eval_stats = mode
        for m in self.modules():
            if isinstance(m, BatchNorm2d):
                m.item_stats = mode == "item" and not self.frozen_batchnorm

    def train(self, mode: bool = True):
        super().train(mode)
        if self.frozen_batchnorm:
            for m in self.modules():
                if isinstance(m, nn.BatchNorm2d):
                    m.eval()
        return self


class ResNetEncoder(EncoderBase):
    """Multi-layer ResNet features. Input (V, 3, H, W) in [0, 1]; normalised to [-1, 1] inside."""

    def __init__(self, backbone: str = "resnet34", num_layers: int = 4, freeze: bool = False,
                 frozen_batchnorm: bool = False, eval_stats: str = "running", context_channels: int = 0,
                 context_dilation: int = 2):
        super().__init__()
        if backbone not in _BLOCKS:
            raise ValueError(f"unknown backbone {backbone!r}")
        self.backbone, self.num_layers = backbone, num_layers
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        inplanes = 64
        # Only the layers that are used are built (layer k is used when num_layers > k).
        for k, (n, planes) in enumerate(zip(_BLOCKS[backbone], _CHANNELS), start=1):
            if num_layers <= k:
                break
            blocks = [BasicBlock(inplanes, planes, 1 if k == 1 else 2)]
            blocks += [BasicBlock(planes, planes) for _ in range(n - 1)]
            setattr(self, f"layer{k}", nn.Sequential(*blocks))
            inplanes = planes
        self.channels = [64] + list(_CHANNELS[: num_layers - 1])
        # image pixels per feature of each map: conv1 2, layer1 4 (after the max pool), then x2 a layer
        self.strides = [2] + [4 * 2 ** k for k in range(num_layers - 1)]
        self.freeze_backbone(freeze, frozen_batchnorm)
        self.backbone_modules = ("conv1", "bn1", *(f"layer{k}" for k in range(1, num_layers)))
        # Built after freezing: the context convolution is never part of pretrained weights.
        self.context = None
        if context_channels > 0:
            d = context_dilation
            self.context = nn.Conv2d(self.channels[-1], context_channels, 3, padding=d, dilation=d)
            self.channels.append(context_channels)
            self.strides.append(self.strides[-1])
        self.latent_size = sum(self.channels)
        self.set_eval_stats(eval_stats)

    def load_weights(self, path: str | Path) -> list[str]:
        """Load a torchvision-style state dict from a local file; returns the ignored keys."""
        path = Path(path)
        state = read_state_dict(path)
        if isinstance(state, dict) and "state_dict" in state:
            state = state["state_dict"]
        own = self.state_dict()
        usable = {k: v for k, v in state.items() if k in own}
        bad = [k for k, v in usable.items() if v.shape != own[k].shape]
        if bad:
            raise UserError(f"encoder weights {path}: shape mismatch for {bad[:3]} (is it a {self.backbone}?)")
        missing = [k for k in own if k not in usable and not k.endswith("num_batches_tracked")
                   and not k.startswith("context.")]
        if missing:
            raise UserError(f"encoder weights {path}: missing {len(missing)} tensors, e.g. {missing[:3]} "
                            f"(expected a torchvision {self.backbone} state dict)")
        self.load_state_dict(usable, strict=False)
        return sorted(set(state) - set(usable))

    def forward(self, images: Tensor) -> list[Tensor]:
        """images (V, 3, H, W) in [0, 1] -> list of feature maps (V, C_l, H/2^.., W/2^..)."""
        x = images * 2.0 - 1.0
        x = self.relu(self.bn1(self.conv1(x)))
        feats = [x]
        if self.num_layers > 1:
            x = self.maxpool(x)
            for k in range(1, self.num_layers):
                x = getattr(self, f"layer{k}")(x)
                feats.append(x)
        if self.context is not None:
            feats.append(self.context(x))
        return feats


def index_features(feats: list[Tensor], uv: Tensor, strides: list[int]) -> Tensor:
    """Bilinearly index multi-layer features at pixels.

    Args:
        feats: list of (V, C_l, H_l, W_l) maps of one image size.
        uv: (V, N, 2) pixel coordinates (spec convention: pixel u centred at u) in each view.
        strides: image pixels per feature of each map (``ResNetEncoder.strides``); feature j of a
            map is centred on pixel stride * j.
    Returns:
        (V, N, sum C_l) features (border-padded; callers zero invalid points).
    """
    out = [sample_bilinear(f, uv / stride) for f, stride in zip(feats, strides)]
    return torch.cat(out, dim=1).transpose(1, 2)


def sample_bilinear(fmap: Tensor, ij: Tensor) -> Tensor:
    """Bilinear features of maps (V, C, h, w) at feature coordinates ij (V, N, 2) (feature j centred
    at j, x first), border-padded -> (V, C, N). ``F.grid_sample``; in an ONNX export the same
    arithmetic as four row gathers, which ONNX Runtime runs about 4x faster than its GridSample, and with
    deterministic algorithms on (``train.deterministic``: grid_sample's CUDA backward has no deterministic kernel)."""
    if not (torch.onnx.is_in_onnx_export() or torch.are_deterministic_algorithms_enabled()):
        grid = feature_grid(ij, fmap.shape[-1], fmap.shape[-2])[:, :, None, :]  # (V, N, 1, 2)
        return F.grid_sample(fmap, grid, mode="bilinear", padding_mode="border", align_corners=False)[..., 0]
    V, C, h, w = fmap.shape
    x, y = ij[..., 0].clamp(0, w - 1), ij[..., 1].clamp(0, h - 1)
    x0, y0 = x.floor(), y.floor()
    wx, wy = (x - x0)[..., None], (y - y0)[..., None]
    x0, y0 = x0.long(), y0.long()
    x1, y1 = (x0 + 1).clamp(max=w - 1), (y0 + 1).clamp(max=h - 1)
    rows = fmap.permute(0, 2, 3, 1).reshape(V * h * w, C)
    base = torch.arange(V, device=fmap.device)[:, None] * (h * w)

    def at(yy: Tensor, xx: Tensor) -> Tensor:
        return rows[(base + yy * w + xx).reshape(-1)].reshape(V, -1, C)

    top, bottom = at(y0, x0), at(y1, x0)  # lerps: three products per feature instead of six
    top = top + (at(y0, x1) - top) * wx
    bottom = bottom + (at(y1, x1) - bottom) * wx
    return (top + (bottom - top) * wy).permute(0, 2, 1)


def feature_grid(ij: Tensor, width: int, height: int) -> Tensor:
    """Feature coordinates (..., 2) (feature j centred at j) -> ``grid_sample`` coordinates with
    ``align_corners=False`` on a ``width`` x ``height`` map (where feature j spans [j - 0.5, j + 0.5])."""
    scale = torch.tensor([2.0 / width, 2.0 / height], device=ij.device, dtype=ij.dtype)
    return (ij + 0.5) * scale - 1.0


def resize_bilinear(fmap: Tensor, size: tuple[int, int]) -> Tensor:
    """``F.interpolate(fmap, size, mode="bilinear", align_corners=False)`` (V, C, h, w) -> (V, C, H, W); with
    deterministic algorithms on, the same arithmetic through ``sample_bilinear`` (bilinear upsampling's CUDA
    backward has no deterministic kernel)."""
    if not torch.are_deterministic_algorithms_enabled():
        return F.interpolate(fmap, size=size, mode="bilinear", align_corners=False)
    (V, C, h, w), (H, W) = fmap.shape, size
    x = ((torch.arange(W, device=fmap.device, dtype=fmap.dtype) + 0.5) * (w / W) - 0.5).clamp_min(0)
    y = ((torch.arange(H, device=fmap.device, dtype=fmap.dtype) + 0.5) * (h / H) - 0.5).clamp_min(0)
    yy, xx = torch.meshgrid(y, x, indexing="ij")
    ij = torch.stack([xx, yy], dim=-1).reshape(1, -1, 2).expand(V, -1, -1)
    return sample_bilinear(fmap, ij).reshape(V, C, H, W)
