"""The paper's aggregation of per-sample YOLO values along each ray (eqs. 4.2-4.4).

    confidence_i   = sigmoid(obj_i)                        (0 for invalid samples)
    ray_confidence = max_i confidence_i
    values_ray     = sum_i values_i * confidence_i / sum_i confidence_i     (box, class logits)
    depth_ray      = sum_i t_i * confidence_i / sum_i confidence_i          (distance estimate, metres)

The weights get a small floor (``eps`` per sample), so when every confidence vanishes the
result is the plain mean over valid samples: finite, never NaN (the original's first NaN source).

Example::

    out = YoloRayRenderer()(raw, t, sample_valid)    # raw (R, S, A, 5+C)
    out.ray_confidence                                # (R, A)
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn


@dataclass
class RayOutputs:
    ray_confidence: Tensor  # (R, A) in [0, 1]
    box: Tensor  # (R, A, 4) raw (tx, ty, tw, th)
    class_logits: Tensor  # (R, A, C)
    depth: Tensor  # (R, A) confidence-weighted distance along the ray, metres
    # Not per ray: the source views' predicted planar depth maps (V, H_f, W_f), metres, of a model
    # with model.surface_depth (None otherwise); reshape and scatter pass it on unchanged.
    surface_depth: Tensor | None = None

    @staticmethod
    def cat(parts: list["RayOutputs"]) -> "RayOutputs":
        return RayOutputs(*(torch.cat([getattr(p, f) for p in parts]) for f in
                            ("ray_confidence", "box", "class_logits", "depth")))

    def scatter(self, index: Tensor, total: int) -> "RayOutputs":
        """These rendered rays placed at ``index`` among ``total`` rays; the others get confidence,
        box and class logits 0 and depth NaN (not rendered: no estimate)."""
        def place(x: Tensor, fill: float) -> Tensor:
            return x.new_full((total, *x.shape[1:]), fill).index_copy(0, index, x)
        return RayOutputs(place(self.ray_confidence, 0.0), place(self.box, 0.0), place(self.class_logits, 0.0),
                          place(self.depth, float("nan")), self.surface_depth)

    def reshape(self, *shape: int) -> "RayOutputs":
        """(R, ...) -> (*shape, ...) on the leading axis."""
        return RayOutputs(*(getattr(self, f).reshape(*shape, *getattr(self, f).shape[1:]) for f in
                            ("ray_confidence", "box", "class_logits", "depth")), self.surface_depth)


class YoloRayRenderer(nn.Module):
    def __init__(self, eps: float = 1e-5):
        super().__init__()
        self.eps = eps

    def forward(self, raw: Tensor, t: Tensor, sample_valid: Tensor) -> RayOutputs:
        """
        Args:
            raw: (R, S, A, 5 + C) MLP outputs per sample.
            t: (R, S) sample distances along the unit rays.
            sample_valid: (R, S) bool, samples inside the sampling interval (slab clipping).
        """
        m = sample_valid.to(raw.dtype)[..., None]  # (R, S, 1)
        conf = torch.sigmoid(raw[..., 0]) * m  # (R, S, A)
        ray_conf = conf.max(dim=1).values
        w = (conf + self.eps) * m
        w = w / w.sum(dim=1, keepdim=True).clamp_min(1e-12)  # (R, S, A); all-invalid rays -> 0
        values = (raw[..., 1:] * w[..., None]).sum(dim=1)  # (R, A, 4 + C)
        depth = (t[..., None] * w).sum(dim=1)
        return RayOutputs(ray_conf, values[..., :4], values[..., 4:], depth)
