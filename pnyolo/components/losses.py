"""The YOLO loss of the paper (section 4.2.1) on rendered ray outputs.

* no-object: BCE of the ray confidence against 0 on cells/anchors without an object;
* object: MSE of the ray confidence against the IoU of the decoded box with its target
  (``model.loss.obj_target: iou``, the paper) or against 1 (``one``: confidence then means "an object
  is here", not "and my box is good"; it separates objects from background faster). With
  ``model.loss.obj_loss: bce`` the object term is binary cross-entropy instead of MSE: its gradient on
  the logit is (p - target), where MSE's is 2 (p - target) p (1 - p), which vanishes for a
  confidently missed object (p near 0), the hard positives such as fully hidden road users;
* box: MSE of (sigmoid tx, sigmoid ty, tw, th) against (x, y, log(w/anchor), log(h/anchor));
* box overlap (``model.loss.iou`` > 0, not in the paper): 1 - generalised IoU of the decoded box with
  its target, so an offset counts relative to the box's size (GIoU, as later YOLOs use IoU-type
  box losses);
* class: cross-entropy of the class logits;
* distance (``model.loss.depth`` > 0, not in the paper): Huber loss (delta 1 m) of the ray's rendered
  distance against the object's distance from the camera, for models that render one (the
  single-view model's distance is NaN: no term). The rendered distance is the confidence-weighted
  mean of the sample distances, so this term moves each anchor's confidence along the ray to its
  own object: the road user in front and the one it hides get different distances;
* surface depth (``model.loss.surface_depth`` > 0 with ``model.surface_depth``, not in the paper):
  ``surface_depth_loss``, the mean absolute log-depth error of the predicted depth maps, an
  auxiliary term added by training (``pnyolo.models.pixelnerf_yolo.PixelNeRFYolo.loss``).

Object, box, overlap, class and distance terms are means over the objects weighted by the target's weight channel
(``model.loss.hidden_weight`` for objects fully hidden in the view that another source view sees,
``model.loss.unseen_weight`` for those no source view sees, else 1), divided by the number of objects
of non-zero weight; an object of weight 0 counts in no term (neither object nor no-object): it is
ignored. With all weights 1 these are the plain means of the paper's loss.

Weights default to box 1, object 20, no-object 1, class 1. Ignored anchors (obj = -1) count
in no term except box/class (they have none).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pnyolo.components.boxes import elementwise_iou_cxcywh, generalized_iou_cxcywh
from pnyolo.config.model import YoloLossConfig
from pnyolo.data.targets import DISTANCE, OBJ, decode_boxes, target_boxes

PROB_EPS = 1e-7


class YoloLoss(nn.Module):
    def __init__(self, cfg: YoloLossConfig | None = None):
        super().__init__()
        self.cfg = cfg or YoloLossConfig()

    def forward(self, ray_confidence: Tensor, box: Tensor, class_logits: Tensor, target: Tensor,
                anchors: Tensor, depth: Tensor | None = None) -> tuple[Tensor, dict[str, float]]:
        """
        Args:
            ray_confidence: (..., S_h, S_w, A) probabilities.
            box: (..., S_h, S_w, A, 4) raw (tx, ty, tw, th).
            class_logits: (..., S_h, S_w, A, C).
            target: (..., S_h, S_w, A, 8) from ``build_targets``.
            anchors: (A, 2).
            depth: (..., S_h, S_w, A) rendered distances in metres (None or NaN: no distance term).
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
            t_obj = target[obj]
            w = t_obj[:, 6]
            n_obj = (w > 0).sum().clamp_min(1)

            def weighted_mean(per_object: Tensor) -> Tensor:
                return (w * per_object).sum() / n_obj

            if self.cfg.iou > 0 or self.cfg.obj_target != "one":
                decoded, wanted = decode_boxes(box, anchors)[obj], target_boxes(target)[obj]
            if self.cfg.obj_target == "one":
                obj_t = torch.ones_like(ray_confidence[obj])
            else:
                with torch.no_grad():
                    obj_t = elementwise_iou_cxcywh(decoded, wanted)
            if self.cfg.obj_loss == "bce":
                l_obj = weighted_mean(F.binary_cross_entropy(p[obj], obj_t, reduction="none"))
            else:
                l_obj = weighted_mean((ray_confidence[obj] - obj_t) ** 2)
            a = anchors.expand(*target.shape[:-1], 2)[obj]
            pred_box = torch.cat([torch.sigmoid(box[obj][:, :2]), box[obj][:, 2:]], dim=-1)
            tgt_box = torch.cat([t_obj[:, 1:3], torch.log(t_obj[:, 3:5].clamp_min(1e-8) / a)], dim=-1)
            l_box = weighted_mean(((pred_box - tgt_box) ** 2).mean(-1))
            l_iou = weighted_mean(1 - generalized_iou_cxcywh(decoded, wanted)) if self.cfg.iou > 0 else zero
            l_cls = weighted_mean(F.cross_entropy(class_logits[obj], t_obj[:, 5].long(), reduction="none"))
            l_depth = zero
            if self.cfg.depth > 0 and depth is not None:
                d = depth[obj]
                has = torch.isfinite(d) & (t_obj[:, DISTANCE] > 0)
                if has.any():
                    per_object = torch.zeros_like(w)
                    per_object[has] = F.smooth_l1_loss(d[has], t_obj[has, DISTANCE], beta=1.0, reduction="none")
                    l_depth = weighted_mean(per_object)
        else:
            l_obj = l_box = l_cls = l_depth = l_iou = zero
        c = self.cfg
        terms = {"box": c.box * l_box, "obj": c.obj * l_obj, "noobj": c.noobj * l_noobj, "cls": c.cls * l_cls}
        if c.iou > 0:
            terms["iou"] = c.iou * l_iou
        if c.depth > 0:
            terms["depth"] = c.depth * l_depth
        total = sum(terms.values())
        return total, {k: float(v.detach()) for k, v in terms.items()}


def surface_depth_loss(predicted: Tensor, rendered: Tensor, stride: int) -> Tensor:
    """Mean |log predicted - log rendered| over the pixels of known depth: predicted (V, h, w)
    depth maps at the feature resolution (feature j centred on pixel stride * j), rendered (V, H, W)
    at the image's (NaN: unknown), taken at those centre pixels. Relative, so a metre counts more
    near the camera."""
    h, w = predicted.shape[-2:]
    target = rendered[:, ::stride, ::stride][:, :h, :w]
    if target.shape[-2:] != (h, w):  # a map larger than the image's centres (odd sizes): repeat the edge
        target = F.pad(target[:, None], (0, w - target.shape[-1], 0, h - target.shape[-2]), mode="replicate")[:, 0]
    known = torch.isfinite(target) & (target > 0)
    if not known.any():
        return predicted.sum() * 0.0
    return (predicted[known].log() - target[known].log()).abs().mean()
