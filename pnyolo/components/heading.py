"""A road user's heading as its axis and a direction (the bev head's and pixelNeRF-YOLO's encoding).

A symmetric road user looks alike facing yaw and yaw + pi, so a regression to (sin, cos) of the yaw learns the mean of
the two (nothing); the axis, (sin, cos) of twice the yaw, is what an image shows, and a separate sign says which way
along it the road user faces::

    sin2, cos2, front = heading_targets(yaw)      # front +1 / -1
    yaw = decode_heading(sin2, cos2, front)        # front: a target's sign or an output's logit
"""
from __future__ import annotations

import math

import torch
from torch import Tensor


def heading_encoding(yaw: Tensor) -> Tensor:
    """(..., 3) [sin 2 yaw, cos 2 yaw, front] of headings (...,): the axis, and front +1 where the heading is the axis
    angle in (-pi/2, pi/2] (-1: that angle plus pi)."""
    sin2, cos2 = torch.sin(2 * yaw), torch.cos(2 * yaw)
    axis = torch.atan2(sin2, cos2) / 2
    front = torch.where(torch.cos(yaw - axis) > 0, torch.ones_like(yaw), -torch.ones_like(yaw))
    return torch.stack([sin2, cos2, front], dim=-1)


def heading_targets(yaw: float) -> tuple[float, float, float]:
    """``heading_encoding`` of one heading, as floats."""
    sin2, cos2, front = heading_encoding(torch.tensor(float(yaw), dtype=torch.float64)).tolist()
    return sin2, cos2, front


def decode_heading(sin2: Tensor, cos2: Tensor, front: Tensor) -> Tensor:
    """The heading (radians) of axis values and the front (a target's sign, an output's logit): the axis angle, turned
    by pi where front < 0."""
    axis = torch.atan2(sin2, cos2) / 2
    return torch.where(front >= 0, axis, axis + math.pi)
