"""Training augmentation of an item's views that keeps the multi-view geometry exact.

    imgs = color_jitter(imgs, hue=0.1, strength=0.1)          # (V, 3, H, W): one jitter for all views
    rgb = mirror_and_shift(rgb, mirrored=True, shift=(3, -2))  # (H, W, ...) as the item sees it
    box = item_box(label_box, width, sx, sy, True, (3, -2))    # the label box in that image

Mirroring flips every image and mirrors every camera (``dataset_spec.camera.mirror_camera``);
a shift moves the principal point with the pixels (``translate_intrinsics``).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from dataset_spec.boxes import box_area, clip_box_to_image, flip_box_x


def color_jitter(images: torch.Tensor, hue: float, strength: float, generator=None) -> torch.Tensor:
    """The same random brightness/contrast/saturation/hue change for all views (V, 3, H, W)."""
    def u(lo, hi):
        return float(lo + (hi - lo) * torch.rand((), generator=generator))
    b, c, s, h = u(1 - strength, 1 + strength), u(1 - strength, 1 + strength), u(1 - strength, 1 + strength), u(-hue, hue)
    x = images * b
    gray = (0.299 * x[:, 0] + 0.587 * x[:, 1] + 0.114 * x[:, 2])[:, None]
    x = (x - gray.mean(dim=(2, 3), keepdim=True)) * c + gray.mean(dim=(2, 3), keepdim=True)
    gray = (0.299 * x[:, 0] + 0.587 * x[:, 1] + 0.114 * x[:, 2])[:, None]
    x = gray + (x - gray) * s
    # Hue: rotate chroma in YIQ space by h turns.
    to_yiq = torch.tensor([[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]])
    a = 2 * math.pi * h
    rot = torch.tensor([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    m = torch.linalg.inv(to_yiq) @ rot @ to_yiq
    x = torch.einsum("ij,vjhw->vihw", m, x)
    return x.clamp(0, 1)


def item_box(box, width: int, sx: float, sy: float, mirrored: bool, shift: tuple[int, int] = (0, 0)) -> np.ndarray:
    """A label box (original image pixels) in an item's resized, possibly mirrored, shifted image."""
    box = flip_box_x(box, width) if mirrored else np.asarray(box, dtype=np.float64)
    dx, dy = shift
    return box * [sx, sy, sx, sy] + 0.5 * np.array([sx, sy, sx, sy]) - 0.5 + [dx, dy, dx, dy]


def shift_image(rgb: np.ndarray, dx: int, dy: int, fill: float = 0) -> np.ndarray:
    """(H, W, ...) image with its content moved by whole pixels (u -> u + dx, v -> v + dy); the
    uncovered border is ``fill`` (black)."""
    h, w = rgb.shape[:2]
    out = np.full_like(rgb, fill)
    if abs(dx) < w and abs(dy) < h:
        out[max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0)] = rgb[max(-dy, 0):h - max(dy, 0), max(-dx, 0):w - max(dx, 0)]
    return out


def mirror_and_shift(image: np.ndarray, mirrored: bool, shift: tuple[int, int], fill: float = 0) -> np.ndarray:
    """An item view's (H, W, ...) array as the item sees it: mirrored left-right when ``mirrored``,
    then moved by ``shift`` (``shift_image``; the uncovered border ``fill``)."""
    if mirrored:
        image = np.ascontiguousarray(image[:, ::-1])
    return shift_image(image, *shift, fill=fill) if shift != (0, 0) else image


def clip_shifted_box(box: np.ndarray, width: int, height: int) -> np.ndarray | None:
    """A label box after an image shift, clipped to the image; None when less than half of its
    area is left in the frame."""
    clipped = clip_box_to_image(box, width, height)
    return clipped if clipped is not None and box_area(clipped) >= 0.5 * box_area(box) else None
