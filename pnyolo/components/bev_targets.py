"""Targets of the ``bev`` model on its ground-plane grid (CenterNet style), and their decoding.

Per class a centre heatmap: a Gaussian around the cell holding each road user's box centre, peak 1
there (radius from the box footprint, ``gaussian_radius``); per road user at its centre cell the
regression values ``[dx, dy, z, log l, log w, log h, sin 2yaw, cos 2yaw, front]`` (dx, dy: the centre within
the cell, in [0, 1); z: the box centre height, metres). The heading is its axis (2 yaw: a box and the same box
turned by 180 degrees have one axis, which a footprint on the ground shows) and which way along the axis it faces
(``front`` +1: yaw is the axis angle in (-90, 90] degrees, -1: that angle plus 180; its sign is what decodes, the
outputs' a logit), as
SECOND's direction classifier: regressing (sin, cos) of yaw itself learns the mean of a symmetric road user's two
headings, a vector near 0 whose angle is noise. Road users the model is not asked about
(no scored view's ground truth holds them: too far, out of every view, left out by the label
thresholds) are real, so the heatmap loss ignores the cells around them instead of calling them
background.

Example::

    t = bev_targets(item.boxes_3d, item.box_classes, positives, grid, num_classes=2)
    t.heatmap.shape          # (C, ny, nx)
    boxes = decode_regression(t.regression, t.cells, grid)   # (P, 7) the same boxes back
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from pnyolo.components.bev_grid import BevGrid
from pnyolo.components.heading import decode_heading, heading_targets
from pnyolo.data.item import Item

REGRESSION = ("dx", "dy", "z", "log_l", "log_w", "log_h", "sin_2yaw", "cos_2yaw", "front")
MIN_OVERLAP = 0.1  # CenterPoint's overlap for the Gaussian radius of ground-plane boxes


@dataclass
class BevTargets:
    heatmap: Tensor  # (C, ny, nx) in [0, 1]: 1 at each positive's centre cell
    weight: Tensor  # (ny, nx) 1, 0 around road users that are neither positive nor background
    cells: Tensor  # (P,) long: flat index iy * nx + ix of each positive's centre cell
    regression: Tensor  # (P, 9) see REGRESSION
    classes: Tensor  # (P,) long
    rows: Tensor  # (P,) long: the positives' rows in the item's boxes_3d


def positive_rows(item: Item) -> list[int]:
    """Rows of ``item.boxes_3d`` in the ground truth of some scored view: what the model must find."""
    return sorted({int(r) for v in item.scored for r in item.gt[v].object_rows})


def gaussian_radius(length: float, width: float, min_overlap: float = MIN_OVERLAP) -> float:
    """CenterNet's radius (in the units of length and width) within which a box corner may move
    and keep ``min_overlap`` IoU with the original: the smallest of its three cases."""
    a1, b1, c1 = 1.0, length + width, length * width * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + math.sqrt(max(b1 * b1 - 4 * a1 * c1, 0.0))) / 2
    a2, b2, c2 = 4.0, 2 * (length + width), (1 - min_overlap) * length * width
    r2 = (b2 + math.sqrt(max(b2 * b2 - 4 * a2 * c2, 0.0))) / 2
    a3, b3, c3 = 4 * min_overlap, -2 * min_overlap * (length + width), (min_overlap - 1) * length * width
    r3 = (b3 + math.sqrt(max(b3 * b3 - 4 * a3 * c3, 0.0))) / 2
    return min(r1, r2, r3)


def _disc(grid: BevGrid, iy: int, ix: int, radius: int) -> tuple[slice, slice, Tensor]:
    """The grid window around (iy, ix) within ``radius`` cells and the squared distances in it."""
    y0, y1 = max(0, iy - radius), min(grid.ny, iy + radius + 1)
    x0, x1 = max(0, ix - radius), min(grid.nx, ix + radius + 1)
    dy = torch.arange(y0, y1, dtype=torch.float32)[:, None] - iy
    dx = torch.arange(x0, x1, dtype=torch.float32)[None, :] - ix
    return slice(y0, y1), slice(x0, x1), dy * dy + dx * dx


def bev_targets(boxes: Tensor, box_classes: Tensor, positives: list[int], grid: BevGrid, num_classes: int,
                min_radius: int = 2) -> BevTargets:
    """Targets for ``boxes`` (N, 7) world [cx, cy, cz, l, w, h, yaw] of classes (N,): the rows in
    ``positives`` are objects, every other row inside the grid is ignored around its centre."""
    heat = torch.zeros(num_classes, grid.ny, grid.nx)
    weight = torch.ones(grid.ny, grid.nx)
    cells, reg, classes, rows = [], [], [], []
    pos = set(positives)
    for n in range(boxes.shape[0]):
        cx, cy, cz, length, width, height, yaw = (float(v) for v in boxes[n])
        fx, fy = (cx - grid.x0) / grid.cell, (cy - grid.y0) / grid.cell
        ix, iy = int(math.floor(fx)), int(math.floor(fy))
        if not (0 <= ix < grid.nx and 0 <= iy < grid.ny):
            continue
        radius = max(min_radius, int(gaussian_radius(length / grid.cell, width / grid.cell)))
        ys, xs, d2 = _disc(grid, iy, ix, radius)
        if n not in pos:
            weight[ys, xs] = torch.where(d2 <= radius * radius, torch.zeros_like(d2), weight[ys, xs])
            continue
        c = int(box_classes[n])
        sigma = (2 * radius + 1) / 6
        heat[c, ys, xs] = torch.maximum(heat[c, ys, xs], torch.exp(-d2 / (2 * sigma * sigma)))
        cells.append(iy * grid.nx + ix)
        reg.append([fx - ix, fy - iy, cz, math.log(length), math.log(width), math.log(height), *heading_targets(yaw)])
        classes.append(c)
        rows.append(n)
    for cell, c in zip(cells, classes):  # a positive's own cell is never ignored, and exactly 1
        weight.view(-1)[cell] = 1.0
        heat[c].view(-1)[cell] = 1.0
    return BevTargets(heat, weight, torch.tensor(cells, dtype=torch.long),
                      torch.tensor(reg, dtype=torch.float32).reshape(-1, len(REGRESSION)),
                      torch.tensor(classes, dtype=torch.long), torch.tensor(rows, dtype=torch.long))


def decode_regression(values: Tensor, cells: Tensor, grid: BevGrid) -> Tensor:
    """Regression values (P, 9) at flat cells (P,) -> world boxes (P, 7) [cx, cy, cz, l, w, h, yaw]."""
    iy, ix = cells // grid.nx, cells % grid.nx
    cx = grid.x0 + (ix.to(values) + values[:, 0]) * grid.cell
    cy = grid.y0 + (iy.to(values) + values[:, 1]) * grid.cell
    size = torch.exp(values[:, 3:6].clamp(max=4.0))
    yaw = decode_heading(values[:, 6], values[:, 7], values[:, 8])
    return torch.stack([cx, cy, values[:, 2], size[:, 0], size[:, 1], size[:, 2], yaw], dim=-1)
