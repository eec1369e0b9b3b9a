"""Surface depth (``model.surface_depth``, not in the paper): a depth map per view from the encoder,
and where a 3D sample lies relative to the surface each view sees.

    head = SurfaceDepthHead(channels=192)
    depth = head([layer1_maps, context_maps])        # (V, H_f, W_f) metres
    cue = surface_cue(z_in_view, depth_at_pixel)     # (..., 2) in (-1, 1)

A point on a surface one view sees, behind what its own view sees, is what a road user hidden in
its own view looks like.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor, nn


class SurfaceDepthHead(nn.Module):
    """Each view's planar depth (metres) from the encoder's deepest maps (its last layer and the
    context maps, one resolution): feats [(V, C_l, H_f, W_f)] -> (V, H_f, W_f). Log-depth output
    around 10 m, bounded to [10 e^-5, 10 e^5] m so a wild early step stays finite."""

    def __init__(self, channels: int, hidden: int = 32):
        super().__init__()
        self.net = nn.Sequential(nn.Conv2d(channels, hidden, 3, padding=1), nn.ReLU(), nn.Conv2d(hidden, 1, 1))

    def forward(self, feats: list[Tensor]) -> Tensor:
        return torch.exp(self.net(torch.cat(feats, dim=1))[:, 0].clamp(-5, 5) + math.log(10.0))


CUE_SCALES_M = (2.0, 8.0)  # surface_cue: tanh(dz / scale) at these scales


def surface_cue(z: Tensor, surface: Tensor) -> Tensor:
    """Where points lie relative to the surface a view sees at their pixels: z (...) their planar
    depth in the view, surface (...) the view's depth there -> (..., len(CUE_SCALES_M)) in (-1, 1):
    0 on the surface, + behind it (hidden from that view), - in front (free space it sees through)."""
    dz = (z - surface)[..., None]
    return torch.tanh(dz / dz.new_tensor(CUE_SCALES_M))

