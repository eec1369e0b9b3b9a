"""The ground-plane model's parts: pooling the views' pillar features per cell, and the grid network.

    pooled = pool_views(features, valid, view_sets)     # (V, C, N), (V, N) -> (B, 2C + 1, N)
    net = BevNet(in_channels, hidden=32, dilations=[1, 2, 4], out_channels=C + 8)
    out = net(grid_features)                            # (B, in, ny, nx) -> (B, out, ny, nx)

Pooling is over the views that see a point (in front of the camera, inside the image): the mean
and the maximum of their features and the share of the views that see it; a point no view sees
gets zeros. A view set (a row of ``view_sets``) says which views a batch entry pools: all of them,
or one alone (own view only, each car on its own for late fusion).
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from pnyolo.components.encoder import resize_bilinear

GROUPS = 8  # group norm groups: per-item statistics, the same in training and evaluation


def pool_views(features: Tensor, valid: Tensor, view_sets: Tensor) -> Tensor:
    """features (V, C, N) of N points in each view, valid (V, N) bool, view_sets (B, V) bool
    -> (B, 2C + 1, N): mean and max over the views of each set that see the point, and their
    share of the set."""
    out = []
    for keep in view_sets:
        ok = (valid & keep[:, None])[:, None]  # (V, 1, N)
        count = ok.sum(0).to(features.dtype)  # (1, N)
        mean = (features * ok).sum(0) / count.clamp_min(1)
        peak = features.masked_fill(~ok, -1e4).max(0).values
        peak = peak.masked_fill(count == 0, 0.0)
        out.append(torch.cat([mean, peak, count / keep.sum().clamp_min(1)], dim=0))
    return torch.stack(out)


def conv_norm(cin: int, cout: int, kernel: int = 3, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, kernel, stride, dilation * (kernel // 2), dilation, bias=False),
                         nn.GroupNorm(min(GROUPS, cout), cout), nn.ReLU(inplace=True))


class Residual(nn.Module):
    def __init__(self, body: nn.Module):
        super().__init__()
        self.body = body

    def forward(self, x: Tensor) -> Tensor:
        return x + self.body(x)


class BevNet(nn.Module):
    """1x1 stem at full resolution, a strided convolution to half resolution, dilated residual
    blocks there (a receptive field of several metres: a car's length, a pedestrian's occluder),
    upsampled and joined with the stem, a 3x3 convolution and 1x1 heads at full resolution."""

    def __init__(self, in_channels: int, hidden: int, dilations: list[int], out_channels: int):
        super().__init__()
        self.stem = conv_norm(in_channels, hidden, kernel=1)
        self.down = conv_norm(hidden, 2 * hidden, stride=2)
        self.blocks = nn.Sequential(*(Residual(conv_norm(2 * hidden, 2 * hidden, dilation=d)) for d in dilations))
        self.fuse = conv_norm(3 * hidden, hidden)
        self.head = nn.Conv2d(hidden, out_channels, 1)

    def forward(self, x: Tensor) -> Tensor:
        """(B, in, ny, nx), ny and nx even -> (B, out, ny, nx)."""
        full = self.stem(x)
        half = self.blocks(self.down(full))
        up = resize_bilinear(half, full.shape[-2:])
        return self.head(self.fuse(torch.cat([full, up], dim=1)))
