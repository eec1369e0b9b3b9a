"""The ground-plane model's loss (CenterNet / CenterPoint):

* heatmap (``model.loss.heatmap``): penalty-reduced focal loss on each class's centre heatmap,
  alpha 2, beta 4: -(1 - p)^2 log p at centre cells, -(1 - y)^4 p^2 log(1 - p) elsewhere (y the
  Gaussian target, so cells near a centre are barely punished), divided by the number of road
  users; cells around road users that are neither target nor background weigh 0;
* box (``model.loss.regression``): L1 at each road user's centre cell on its centre offset in the cell,
  centre height (metres), log length / width / height and (sin, cos) of twice the yaw (its axis), the mean over
  road users of each group, and binary cross-entropy on which way along the axis it faces (``front``), summed.

    loss, terms = bev_loss(out, item, cfg.model.loss, cfg.model.bev.min_radius, "cpu")   # out: BevOutputs
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from pnyolo.config.model import CentreLossConfig
from pnyolo.components.bev_targets import bev_targets, positive_rows
from pnyolo.data.item import Item

ALPHA, BETA = 2.0, 4.0
GROUPS = {"offset": slice(0, 2), "height": slice(2, 3), "size": slice(3, 6), "yaw": slice(6, 8)}  # L1 terms
FRONT = 8  # the regression channel of the heading's direction (a logit)


def centre_focal_loss(logits: Tensor, target: Tensor, weight: Tensor) -> Tensor:
    """logits and targets (C, ny, nx), weight (ny, nx) -> the summed loss over the number of centres."""
    pos = target >= 1.0
    log_p, log_not_p = F.logsigmoid(logits), F.logsigmoid(-logits)
    p = torch.sigmoid(logits)
    loss = torch.where(pos, -log_p * (1 - p) ** ALPHA, -log_not_p * p ** ALPHA * (1 - target) ** BETA)
    return (loss * weight[None]).sum() / pos.sum().clamp_min(1)


def bev_loss(out, item: Item, cfg: CentreLossConfig, min_radius: int, device) -> tuple[Tensor, dict[str, float]]:
    """The loss of a ``BevOutputs`` for its item (every view pooled: batch entry 0); ``min_radius``:
    the smallest heatmap radius in cells (``model.bev.min_radius``)."""
    t = bev_targets(item.boxes_3d, item.box_classes, positive_rows(item), out.grid, out.heatmap.shape[1],
                    min_radius)
    heat = centre_focal_loss(out.heatmap[0], t.heatmap.to(device), t.weight.to(device))
    terms = {"heatmap": float(heat.detach())}
    loss = cfg.heatmap * heat
    if len(t.cells):
        pred = out.regression[0].reshape(out.regression.shape[1], -1)[:, t.cells.to(device)].T  # (P, 9)
        target = t.regression.to(device)
        diff = (pred - target).abs()
        box = F.binary_cross_entropy_with_logits(pred[:, FRONT], (target[:, FRONT] > 0).to(pred.dtype))  # +1 / -1
        terms["front"] = float(box.detach())
        for name, cols in GROUPS.items():
            term = diff[:, cols].mean()
            terms[name] = float(term.detach())
            box = box + term
        loss = loss + cfg.regression * box
    return loss, terms
