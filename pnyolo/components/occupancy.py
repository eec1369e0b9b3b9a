"""Per-sample 3D supervision (``model.loss.occupancy``): which samples lie inside the road user a cell is for.

The paper supervises each ray only through its aggregate (maximum confidence, a confidence-weighted
box), so nothing tells the MLP which 3D point holds the road user, and an occluder and the road
user behind it on one ray blend. Here every rendered sample of a cell's ray is a target of its own,
for each anchor:

* positive: the sample lies inside the 3D box of the road user assigned to that cell and anchor (a
  coarse sample of hierarchical sampling, which stands for its bin t +- half_width: the bin meets
  the box; one that stands for its cell's frustum segment, ``model.sampler.footprint`` frustum: the
  segment meets the box); a road user hidden in the target view is treated like any other: only another
  view can show the MLP that the point holds it;
* ignored: the anchor is ignored by the YOLO targets, or the sample lies inside another road user's
  box (one assigned to another cell or anchor, or left out of the ground truth): not background;
* negative: inside no road user's box.

Confidence: binary cross-entropy, positives and negatives averaged separately (positives are a few
samples in thousands) and added; class cross-entropy and the YOLO box terms on the positives, so
each sample near its road user predicts that road user's box (what depth peaks decode).

Example::

    out = model(..., return_samples=True)
    loss, terms = OccupancyLoss(cfg.model.loss.occupancy)(out.samples, item.targets, item.boxes_3d, model.anchors)
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pnyolo.components.renderer import SampleOutputs
from pnyolo.data.targets import IGNORE, OBJ, OBJECT

EPS = 1e-7


def ray_box_intervals(origins: Tensor, dirs: Tensor, boxes: Tensor) -> tuple[Tensor, Tensor]:
    """Where rays (R, 3), (R, 3) enter and leave oriented boxes (N, 7) [cx, cy, cz, l, w, h, yaw]:
    t_in, t_out (R, N) in metres along the ray (slab method in each box's frame); a ray that
    misses a box has t_in > t_out."""
    c, s = torch.cos(boxes[:, 6]), torch.sin(boxes[:, 6])
    # world -> box frame: rotate by -yaw about z, after moving the centre to the origin
    rel = origins[:, None, :] - boxes[None, :, :3]  # (R, N, 3)

    def to_box(v: Tensor) -> Tensor:
        return torch.stack([c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1], v[..., 2]], dim=-1)
    o = to_box(rel)
    d = to_box(dirs[:, None, :].expand_as(rel))
    half = boxes[None, :, 3:6] / 2
    safe = torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
    t0, t1 = (-half - o) / safe, (half - o) / safe
    t_in = torch.minimum(t0, t1).max(dim=-1).values
    t_out = torch.maximum(t0, t1).min(dim=-1).values
    return t_in, t_out


def segments_meet_boxes(origins: Tensor, dirs: Tensor, t: Tensor, half: Tensor, lateral: Tensor,
                        boxes: Tensor) -> Tensor:
    """(R, S, N) bool: each frustum segment of rays (R, 3), (R, 3) (its bin t +- half (R, S) along the ray,
    ``lateral`` (R, S) either side of it) meets each box (N, 7): the ray's bin meets the box grown by the segment's
    half-width on every side."""
    c, s = torch.cos(boxes[:, 6]), torch.sin(boxes[:, 6])
    rel = origins[:, None, :] - boxes[None, :, :3]  # (R, N, 3)

    def to_box(v: Tensor) -> Tensor:
        return torch.stack([c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1], v[..., 2]], dim=-1)
    o = to_box(rel)[:, None]  # (R, 1, N, 3)
    d = to_box(dirs[:, None, :].expand_as(rel))[:, None]
    size = boxes[None, None, :, 3:6] / 2 + lateral[..., None, None]  # (R, S, N, 3)
    safe = torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
    t0, t1 = (-size - o) / safe, (size - o) / safe
    t_in, t_out = torch.minimum(t0, t1).max(dim=-1).values, torch.maximum(t0, t1).min(dim=-1).values  # (R, S, N)
    lo, hi = (t - half)[..., None], (t + half)[..., None]
    return (hi >= t_in) & (lo <= t_out) & (t_in <= t_out)


def sample_targets(samples: SampleOutputs, targets: Tensor, boxes: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Per-sample targets of the rendered rays.

    Args:
        samples: (R, S) samples of rays whose cells index ``targets``.
        targets: (V, S_h, S_w, A, C) the item's YOLO targets (with the object channel).
        boxes: (N, 7) the item's road-user boxes (``item.boxes_3d``).
    Returns:
        positive (R, S, A) bool, counted (R, S, A) bool (not ignored), and each ray's cell targets (R, A, C).
    """
    A, C = targets.shape[-2:]
    cell_t = targets.reshape(-1, A, C)[samples.cell]  # (R, A, C)
    fr = samples.frustums
    R, S = fr.t.shape
    if boxes.numel() and fr.lateral is not None:
        inside = segments_meet_boxes(fr.origins, fr.dirs, fr.t, fr.half, fr.lateral, boxes)
    elif boxes.numel():
        t_in, t_out = ray_box_intervals(fr.origins, fr.dirs, boxes)  # (R, N)
        lo, hi = (fr.t - fr.half)[..., None], (fr.t + fr.half)[..., None]
        inside = (hi >= t_in[:, None]) & (lo <= t_out[:, None]) & (t_in <= t_out)[:, None]  # (R, S, N)
    else:
        inside = torch.zeros(R, S, 0, dtype=torch.bool, device=fr.t.device)
    own = torch.where(cell_t[..., 0] == OBJ, cell_t[..., OBJECT].long() - 1, torch.full_like(cell_t[..., 0], -1).long())
    if inside.shape[-1]:
        positive = inside.gather(2, own.clamp_min(0)[:, None, :].expand(R, S, A)) & (own >= 0)[:, None, :]
    else:
        positive = torch.zeros(R, S, A, dtype=torch.bool, device=fr.t.device)
    in_other = (inside.sum(dim=-1, keepdim=True) - positive.to(torch.long)) > 0  # (R, S, A)
    counted = samples.valid[..., None] & (cell_t[..., 0] != IGNORE)[:, None, :] & (positive | ~in_other)
    return positive, counted, cell_t


class OccupancyLoss(nn.Module):
    def __init__(self, weight: float):
        super().__init__()
        self.weight = weight  # model.loss.occupancy

    def forward(self, samples: SampleOutputs, targets: Tensor, boxes: Tensor, anchors: Tensor
                ) -> tuple[Tensor, dict[str, float]]:
        """The weighted per-sample terms and their values ({"occupancy": ...})."""
        on = samples.frustums.t.device
        positive, counted, cell_t = sample_targets(samples, targets.to(on), boxes.to(on))
        raw = samples.raw
        p = torch.sigmoid(raw[..., 0]).clamp(EPS, 1 - EPS)
        zero = raw.sum() * 0.0
        neg = counted & ~positive
        l_neg = F.binary_cross_entropy(p[neg], torch.zeros_like(p[neg])) if neg.any() else zero
        l_pos = l_cls = l_box = zero
        if positive.any():
            w = cell_t[..., 6][:, None, :].expand_as(positive)[positive]  # the road user's loss weight
            n = w.gt(0).sum().clamp_min(1)
            l_pos = (w * F.binary_cross_entropy(p[positive], torch.ones_like(p[positive]), reduction="none")).sum() / n
            t = cell_t[:, None].expand(*positive.shape, cell_t.shape[-1])[positive]  # (P, C) the positives' targets
            l_cls = (w * F.cross_entropy(raw[..., 5:][positive], t[:, 5].long(), reduction="none")).sum() / n
            a = anchors.to(raw)[None, None].expand(*positive.shape, 2)[positive]
            pred = torch.cat([torch.sigmoid(raw[..., 1:3][positive]), raw[..., 3:5][positive]], dim=-1)
            want = torch.cat([t[:, 1:3], torch.log(t[:, 3:5].clamp_min(1e-8) / a)], dim=-1)
            l_box = (w * ((pred - want) ** 2).mean(-1)).sum() / n
        total = self.weight * (l_pos + l_neg + l_cls + l_box)
        return total, {"occupancy": float(total.detach())}
