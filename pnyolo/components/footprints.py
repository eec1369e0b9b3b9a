"""What a sample stands for in every source view (``model.sampler.footprint: frustum``): a coarse sample of a cell's
ray is the cell's frustum segment between its bin's two depths, and what it reads from each source view covers that
segment's footprint there, as mip-NeRF's conical frustums and Zip-NeRF's multisamples make a sample see its volume.

    half = segment_footprints(centres_cam, radius, fx, fy)      # (V, N, 2) half-sizes (px) of each footprint
    f = index_footprints(maps, uv, half, strides, levels=4)     # (V, N, C): every map max-pooled over it

A segment is bounded by a sphere (centre: the sample, radius from its bin's half-length and the cell's half-width
at that depth, ``segment_radius``); a sphere of radius r centred at camera coordinates (x, y, z), z > r, projects
within f r sqrt(z^2 + x^2) / (z (z - r)) pixels of its centre's projection horizontally (and likewise vertically),
so that axis-aligned box contains the projection of every point of the segment. Each encoder map is max-pooled by 2,
4, 8, ...; a footprint reads the level whose pooled cells are at least as wide as it, taking the maximum over the
2 x 2 pooled cells it can touch: the maximum of the map over a region that contains the whole footprint (a road user
a few pixels wide anywhere in it is not averaged away).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

MIN_DEPTH = 0.05  # metres: a segment closer to a camera than this (or reaching behind it) reads nothing there


def segment_radius(half_length: Tensor, lateral: Tensor) -> Tensor:
    """The radius of a sphere holding a frustum segment: its bin's half-length along the ray and its half-width
    across (at the bin's far end: the cell's square cross-section, so its half-diagonal)."""
    return torch.sqrt(half_length ** 2 + 2 * lateral ** 2)


def segment_footprints(centres: Tensor, radius: Tensor, fx: Tensor, fy: Tensor) -> tuple[Tensor, Tensor]:
    """Half-sizes (V, N, 2) in pixels of the boxes, centred on each segment centre's projection, that contain the
    projection of every point of its bounding sphere; and whether the sphere lies in front of each camera (V, N).

    Args:
        centres: (V, N, 3) segment centres in each camera's frame (OpenCV axes, z forward).
        radius: (N,) the segments' bounding-sphere radii, metres.
        fx, fy: (V,) focal lengths, pixels.
    """
    x, y, z = centres.unbind(-1)
    r = radius[None, :]
    front = z - r > MIN_DEPTH
    depth = torch.where(front, z, torch.ones_like(z))
    near = torch.where(front, z - r, torch.ones_like(z))
    hx = fx[:, None] * r * torch.sqrt(depth ** 2 + x ** 2) / (depth * near)
    hy = fy[:, None] * r * torch.sqrt(depth ** 2 + y ** 2) / (depth * near)
    return torch.stack([hx, hy], dim=-1), front


def footprint_levels(half: Tensor, stride: int, levels: int) -> Tensor:
    """(V, N) long: the pooling level of a map of ``stride`` whose cells (stride * 2^level pixels) are at least as
    wide as each footprint (2 x its half-size), at most ``levels``."""
    width = (2 * half.max(dim=-1).values / stride).clamp_min(1.0)
    return torch.ceil(torch.log2(width) - 1e-6).clamp(0, levels).long()


def pooled_maps(fmap: Tensor, levels: int) -> list[Tensor]:
    """``fmap`` (V, C, h, w) and its max-pooled copies by 2, 4, ... 2^levels (partial windows at the edges kept)."""
    return [fmap] + [F.max_pool2d(fmap, 2 ** k, 2 ** k, ceil_mode=True) for k in range(1, levels + 1)]


def _touched_max(pooled: Tensor, view: Tensor, lo: Tensor) -> Tensor:
    """Max over the 2 x 2 pooled cells from ``lo`` (M, 2: column, row, clamped into the map) of maps (V, C, h, w)
    at ``view`` (M,) -> (M, C)."""
    V, C, h, w = pooled.shape
    rows = pooled.permute(0, 2, 3, 1).reshape(V * h * w, C)
    base = view * (h * w)
    x0, y0 = lo[:, 0].clamp(0, w - 1), lo[:, 1].clamp(0, h - 1)
    x1, y1 = (x0 + 1).clamp(max=w - 1), (y0 + 1).clamp(max=h - 1)
    out = rows[base + y0 * w + x0]
    for yy, xx in ((y0, x1), (y1, x0), (y1, x1)):
        out = torch.maximum(out, rows[base + yy * w + xx])
    return out


def index_footprints(maps: list[Tensor], uv: Tensor, half: Tensor, strides: list[int], levels: int) -> Tensor:
    """Every map's maximum over each footprint (``pnyolo.components.encoder.index_features``' layout).

    Args:
        maps: (V, C_l, H_l, W_l) maps of one image size, feature j of a map centred on pixel stride * j.
        uv: (V, N, 2) footprint centres in pixels; half: (V, N, 2) their half-sizes (``segment_footprints``).
        strides: image pixels per feature of each map; levels: the coarsest pooling level, 2^levels.
    Returns:
        (V, N, sum C_l) features (callers zero the points a view does not see).
    """
    V, N = uv.shape[:2]
    view = torch.arange(V, device=uv.device)[:, None].expand(V, N).reshape(-1)
    lo_px = (uv - half).reshape(-1, 2)  # the footprint's first pixel
    out = []
    for fmap, stride in zip(maps, strides):
        level = footprint_levels(half, stride, levels).reshape(-1)
        res = fmap.new_zeros(V * N, fmap.shape[1])
        for k, pooled in enumerate(pooled_maps(fmap, levels)):
            sel = (level == k).nonzero().squeeze(1)
            if sel.numel():
                # pooled cell j covers pixels [stride (2^k j - 1/2), stride (2^k (j + 1) - 1/2))
                lo = torch.floor((lo_px[sel] / stride + 0.5) / 2 ** k).long()
                res = res.index_copy(0, sel, _touched_max(pooled, view[sel], lo))
        out.append(res.reshape(V, N, -1))
    return torch.cat(out, dim=-1)


@dataclass(frozen=True)
class Segments:
    """The samples a ray-casting model queries, one a row: a ray's bin t +- half along it (a fine sample: half 0)
    and, with ``model.sampler.footprint`` frustum, ``lateral`` either side of it: the frustum segment read over
    its footprint in every source view."""

    origins: np.ndarray  # (P, 3) world
    dirs: np.ndarray  # (P, 3) unit
    t: np.ndarray  # (P,) metres
    half: np.ndarray  # (P,) 0: a fine sample, a point along the ray
    lateral: np.ndarray | None  # (P,); None: every sample read at its point (model.sampler.footprint point)

    def centres(self) -> np.ndarray:
        return self.origins + self.t[:, None] * self.dirs
