"""Which grid rays a training step renders.

Road users fill 1-5 % of the grid cells (the paper, section 4.1.3), yet every cell's ray costs
the same MLP work: most of a step goes to background rays whose no-object loss is already small.
``training_ray_mask`` keeps every cell that holds an object (ignored cells have no loss to render for) and
its neighbours (the cells where duplicate boxes appear), and a random share of the remaining
background cells, drawn anew each step. The no-object term is a mean over the cells in the loss,
so over a random share it stays an unbiased estimate of the mean over all background cells;
cells left out are marked ignored in the targets (``ignore_unrendered``), so no loss term sees
them. Set by ``train.background_rays`` (1: every ray, the paper's training).

``own_view_dropout_mask`` draws the rays of a step whose *target* view's image features are withheld
(``train.own_view_dropout``): their road users must be found from the other source views, the way
a road user hidden in its target view can only be. Road users are fully hidden in their view for a
few percent of the labels, so without this nearly every training ray can be answered from its own
view's features alone, and the other views' features are little used (docs/experiments.md,
runs 36-39). Cells of road users no other view sees are never drawn.

Example::

    mask = training_ray_mask(targets, 0.25)           # (V, S_h, S_w) bool; targets = model.targets(item)
    out = model(images, K, c2w, grid, ray_mask=mask)     # unrendered cells: confidence 0
    loss = loss_fn(..., ignore_unrendered(targets, mask), ...)
    drop = own_view_dropout_mask(unseen, 0.25, mask)    # unseen: data.targets.unseen_elsewhere_cells per view
    out = model(images, K, c2w, grid, ray_mask=mask, drop_own_view=drop)
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from pnyolo.data.targets import IGNORE, OBJ


def training_ray_mask(target: Tensor, background_fraction: float, neighbourhood: int = 1,
                      generator: torch.Generator | None = None) -> Tensor:
    """
    Args:
        target: (V, S_h, S_w, A, C) targets of one item (``build_targets`` per view).
        background_fraction: share in [0, 1] of the other cells to keep, each drawn independently.
        neighbourhood: cells within this many rows/columns of a target cell are always kept.
    Returns:
        (V, S_h, S_w) bool: True for the cells whose rays are rendered.
    """
    occupied = (target[..., 0] == OBJ).any(dim=-1).to(torch.float32)  # (V, S_h, S_w)
    if neighbourhood > 0:
        k = 2 * neighbourhood + 1
        occupied = F.max_pool2d(occupied[:, None], k, stride=1, padding=neighbourhood)[:, 0]
    drawn = torch.rand(occupied.shape, generator=generator) < background_fraction
    return (occupied > 0) | drawn.to(occupied.device)


def own_view_dropout_mask(unseen_elsewhere: Tensor, share: float, rendered: Tensor | None = None,
                          generator: torch.Generator | None = None) -> Tensor | None:
    """The rays whose target view's image features a training step withholds (``train.own_view_dropout``).

    Args:
        unseen_elsewhere: (V, S_h, S_w) bool, cells holding a road user no other source view sees
            (``data.targets.unseen_elsewhere_cells``): never drawn, their labels would be unlearnable.
        share: the probability in [0, 1] of each other cell being drawn.
        rendered: (V, S_h, S_w) bool, the rays the step renders (None: all); only those are drawn.
    Returns:
        (V, S_h, S_w) bool, or None when ``share`` is 0.
    """
    if share <= 0:
        return None
    drawn = torch.rand(unseen_elsewhere.shape, generator=generator) < share
    drawn = drawn.to(unseen_elsewhere.device) & ~unseen_elsewhere
    return drawn if rendered is None else drawn & rendered


def ignore_unrendered(target: Tensor, mask: Tensor) -> Tensor:
    """A copy of ``target`` (V, S_h, S_w, A, C) whose cells outside ``mask`` are ignored (obj -1)."""
    out = target.clone()
    out[..., 0][~mask] = IGNORE
    return out
