"""The YOLO loss of the paper (section 4.2.1) on rendered ray outputs.

* no-object: BCE of the ray confidence against 0 on cells/anchors without an object;
* object: MSE of the ray confidence against the IoU of the decoded box with its target
  (``loss.obj_target: iou``, the paper) or against 1 (``one``: confidence then means "an object
  is here", not "and my box is good"; it separates objects from background faster). With
  ``loss.obj_loss: bce`` the object term is binary cross-entropy instead of MSE: its gradient on
  the logit is (p - target), where MSE's is 2 (p - target) p (1 - p), which vanishes for a
  confidently missed object (p near 0), the hard positives such as fully hidden road users;
* box: MSE of (sigmoid tx, sigmoid ty, tw, th) against (x, y, log(w/anchor), log(h/anchor));
* class: cross-entropy of the class logits.

Weights default to box 1, object 20, no-object 1, class 1. Ignored anchors (obj = -1) count
in no term except box/class (they have none).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .boxes_torch import elementwise_iou_cxcywh
from .config import LossConfig
from .targets import OBJ, decode_boxes, target_boxes

PROB_EPS = 1e-7


class YoloLoss(nn.Module):
    def __init__(self, cfg: LossConfig | None = None):
        super().__init__()
        self.cfg = cfg or LossConfig()

    def forward(self, ray_confidence: Tensor, box: Tensor, class_logits: Tensor, target: Tensor,
                anchors: Tensor) -> tuple[Tensor, dict[str, float]]:
        """
        Args:
            ray_confidence: (..., S_h, S_w, A) probabilities.
            box: (..., S_h, S_w, A, 4) raw (tx, ty, tw, th).
            class_logits: (..., S_h, S_w, A, C).
            target: (..., S_h, S_w, A, 6) from ``build_targets``.
            anchors: (A, 2).
        Returns:
            (total loss, {term: value}) with the weighted terms.
        """
        anchors = anchors.to(box)
        obj = target[..., 0] == OBJ
        noobj = target[..., 0] == 0
        zero = box.sum() * 0.0
        p = ray_confidence.clamp(PROB_EPS, 1 - PROB_EPS)
        l_noobj = F.binary_cross_entropy(p[noobj], torch.zeros_like(p[noobj])) if noobj.any() else zero
        if obj.any():
            if self.cfg.obj_target == "one":
                obj_t = torch.ones_like(ray_confidence[obj])
            else:
                with torch.no_grad():
                    obj_t = elementwise_iou_cxcywh(decode_boxes(box, anchors)[obj], target_boxes(target)[obj])
            if self.cfg.obj_loss == "bce":
                l_obj = F.binary_cross_entropy(p[obj], obj_t)
            else:
                l_obj = F.mse_loss(ray_confidence[obj], obj_t)
            a = anchors.expand(*target.shape[:-1], 2)[obj]
            pred_box = torch.cat([torch.sigmoid(box[obj][:, :2]), box[obj][:, 2:]], dim=-1)
            tgt_box = torch.cat([target[obj][:, 1:3], torch.log(target[obj][:, 3:5].clamp_min(1e-8) / a)], dim=-1)
            l_box = F.mse_loss(pred_box, tgt_box)
            l_cls = F.cross_entropy(class_logits[obj], target[obj][:, 5].long())
        else:
            l_obj = l_box = l_cls = zero
        c = self.cfg
        terms = {"box": c.box * l_box, "obj": c.obj * l_obj, "noobj": c.noobj * l_noobj, "cls": c.cls * l_cls}
        total = sum(terms.values())
        return total, {k: float(v.detach()) for k, v in terms.items()}
