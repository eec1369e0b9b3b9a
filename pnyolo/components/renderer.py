"""The paper's aggregation of per-sample YOLO values along each ray (eqs. 4.2-4.4), and depth peaks.

    confidence_i   = sigmoid(obj_i)                        (0 for invalid samples)
    ray_confidence = max_i confidence_i
    values_ray     = sum_i values_i * confidence_i / sum_i confidence_i     (box, class logits)
    depth_ray      = sum_i t_i * confidence_i / sum_i confidence_i          (distance estimate, metres)

The weights get a small floor (``eps`` per sample), so when every confidence vanishes the
result is the plain mean over valid samples: finite, never NaN (the original's first NaN source).

With ``peaks`` > 1 the renderer also keeps, per ray and anchor, up to that many confidence peaks
along the ray, at least ``gap`` metres apart, each with the values aggregated over its run (the
samples around it with at least half its confidence): an occluder and the road user behind it on
one ray come out as two candidates instead of one blended box (``RayOutputs.peaks``, decoded as
separate detections).

Example::

    out = YoloRayRenderer()(raw, t, sample_valid)          # raw (R, S, A, 5+C)
    out.ray_confidence                                      # (R, A)
    out = YoloRayRenderer()(raw, t, sample_valid, peaks=2, gap=2.0)
    out.peaks.ray_confidence                                # (R, A, 2)
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor, nn

from pnyolo.components.frustums import Frustums

PER_RAY = ("ray_confidence", "box", "class_logits", "depth", "state")
PEAK_RUN = 0.5  # a depth peak's samples: the run around it with at least this share of its confidence


@dataclass
class SampleOutputs:
    """The rendered rays' samples, kept for per-sample losses (``model.loss.occupancy``) and coverage."""

    frustums: Frustums  # each sample's segment of its ray (pnyolo.components.frustums)
    valid: Tensor  # (R, S) bool
    raw: Tensor  # (R, S, A, 5 + C) the MLP's YOLO outputs (its 3D state left out)
    cell: Tensor  # (R,) long: index of the ray's cell among the item's V * S_h * S_w cells

    @staticmethod
    def cat(parts: list["SampleOutputs"]) -> "SampleOutputs":
        return SampleOutputs(Frustums.cat([p.frustums for p in parts]),
                             *(torch.cat([getattr(p, f) for p in parts]) for f in ("valid", "raw", "cell")))

    def points(self) -> Tensor:
        """(R, S, 3) world positions of the samples."""
        return self.frustums.points()


@dataclass
class RayOutputs:
    ray_confidence: Tensor  # (R, A) in [0, 1]
    box: Tensor  # (R, A, 4) raw (tx, ty, tw, th)
    class_logits: Tensor  # (R, A, C)
    depth: Tensor  # (R, A) confidence-weighted distance along the ray, metres
    # Not per ray: the source views' predicted planar depth maps (V, H_f, W_f), metres, of a model
    # with model.surface_depth (None otherwise); reshape and scatter pass it on unchanged.
    surface_depth: Tensor | None = None
    # Depth peaks (``peaks`` > 1): the same fields with a trailing candidate axis, (R, A, K, ...).
    peaks: "RayOutputs | None" = None
    # The samples of the rendered rays (models that render rays; None for the single view).
    samples: SampleOutputs | None = None
    # (R, A, D) each anchor's 3D state (``pnyolo.components.view_state``: D = 6) aggregated like the box; a kind
    # without one has D = 0 (the default).
    state: Tensor | None = None

    def __post_init__(self):
        if self.state is None:
            self.state = self.ray_confidence.new_zeros((*self.ray_confidence.shape, 0))

    def _map(self, fn) -> "RayOutputs":
        """``fn`` applied to every per-ray field, the peaks' included (leading axis R)."""
        peaks = None if self.peaks is None else self.peaks._map(fn)
        return replace(self, **{f: fn(getattr(self, f)) for f in PER_RAY}, peaks=peaks)

    @staticmethod
    def cat(parts: list["RayOutputs"]) -> "RayOutputs":
        peaks = None if parts[0].peaks is None else RayOutputs.cat([p.peaks for p in parts])
        samples = None if parts[0].samples is None else SampleOutputs.cat([p.samples for p in parts])
        return RayOutputs(**{f: torch.cat([getattr(p, f) for p in parts]) for f in PER_RAY}, peaks=peaks,
                          samples=samples)

    def scatter(self, index: Tensor, total: int) -> "RayOutputs":
        """These rendered rays placed at ``index`` among ``total`` rays; the others get confidence,
        box and class logits 0 and depth NaN (not rendered: no estimate). ``samples`` stay as they are
        (they know their cells)."""
        def place(x: Tensor, fill: float) -> Tensor:
            return x.new_full((total, *x.shape[1:]), fill).index_copy(0, index, x)
        peaks = None if self.peaks is None else self.peaks.scatter(index, total)
        return replace(self, **{f: place(getattr(self, f), float("nan") if f == "depth" else 0.0) for f in PER_RAY},
                       peaks=peaks)

    def reshape(self, *shape: int) -> "RayOutputs":
        """(R, ...) -> (*shape, ...) on the leading axis."""
        return self._map(lambda x: x.reshape(*shape, *x.shape[1:]))

    def first_peaks(self, k: int) -> "RayOutputs":
        """These outputs as a pass keeping at most ``k`` depth peaks makes them: the peaks are found one after
        another, so the first ``k`` of more are what ``k`` gives (1: the per-ray values alone)."""
        if self.peaks is None or self.peaks.ray_confidence.shape[-1] <= k:
            return self
        if k <= 1:
            return replace(self, peaks=None)
        p = self.peaks
        return replace(self, peaks=replace(p, ray_confidence=p.ray_confidence[..., :k], box=p.box[..., :k, :],
                                           class_logits=p.class_logits[..., :k, :], depth=p.depth[..., :k],
                                           state=p.state[..., :k, :]))

    def candidates(self) -> "RayOutputs":
        """The detections to decode: the depth peaks (..., A, K, ...) or the per-ray values with K = 1."""
        if self.peaks is not None:
            return self.peaks
        return RayOutputs(self.ray_confidence[..., None], self.box[..., None, :], self.class_logits[..., None, :],
                          self.depth[..., None], state=self.state[..., None, :])


class YoloRayRenderer(nn.Module):
    """``attention``: a module giving the samples' aggregation weights (``pnyolo.components.
    ray_attention.RayTransformer``) in place of their confidences (None: the paper's weighted mean); ``state``: how
    many trailing raw channels are a 3D state (0: none)."""

    def __init__(self, eps: float = 1e-5, attention: nn.Module | None = None, state: int = 0):
        super().__init__()
        self.eps = eps
        self.attention = attention
        self.state = state

    def forward(self, raw: Tensor, t: Tensor, sample_valid: Tensor, peaks: int = 1, gap: float = 2.0) -> RayOutputs:
        """
        Args:
            raw: (R, S, A, 5 + C + state) MLP outputs per sample.
            t: (R, S) sample distances along the unit rays (any order).
            sample_valid: (R, S) bool, samples inside the sampling interval (slab clipping).
            peaks: candidates per ray and anchor to keep (1: the paper's single aggregate only).
            gap: metres at least between peaks.
        """
        m = sample_valid.to(raw.dtype)[..., None]  # (R, S, 1)
        conf = torch.sigmoid(raw[..., 0]) * m  # (R, S, A)
        out = self._aggregate(raw, t, conf, m)
        if peaks > 1:
            out.peaks = self._peaks(raw, t, conf, m, peaks, gap)
        return out

    def _aggregate(self, raw: Tensor, t: Tensor, conf: Tensor, m: Tensor) -> RayOutputs:
        """The paper's per-ray values from confidences (R, S, A) over the samples weighted by ``m``."""
        ray_conf = conf.max(dim=1).values
        if self.attention is not None:
            w = self.attention(raw, t, conf, m)
        else:
            w = (conf + self.eps) * m
            w = w / w.sum(dim=1, keepdim=True).clamp_min(1e-12)  # (R, S, A); all-invalid rays -> 0
        yolo, state = self._split(raw)
        values = (yolo[..., 1:] * w[..., None]).sum(dim=1)  # (R, A, 4 + C)
        return RayOutputs(ray_conf, values[..., :4], values[..., 4:], (t[..., None] * w).sum(dim=1),
                          state=(state * w[..., None]).sum(dim=1))

    def _split(self, raw: Tensor) -> tuple[Tensor, Tensor]:
        """raw (..., 5 + C + state) -> its YOLO values (..., 5 + C), laid out as a raw without a state is (the sums
        over the samples then add the same numbers in the same order: the same outputs to the bit), and its state."""
        c = raw.shape[-1] - self.state
        return (raw[..., :c].contiguous() if self.state else raw), raw[..., c:]

    def _peaks(self, raw: Tensor, t: Tensor, conf: Tensor, m: Tensor, k: int, gap: float) -> RayOutputs:
        """Up to ``k`` peaks (R, A, K, ...): the most confident sample, then the most confident one
        outside every earlier peak's run and at least ``gap`` from its peak sample. A peak's run is
        the samples around it, in depth order, with at least ``PEAK_RUN`` of its confidence: one
        road user's samples, however deep its box; its values are aggregated over that run."""
        order = t.argsort(dim=1)
        t = t.gather(1, order)
        conf = conf.gather(1, order[..., None].expand_as(conf))
        yolo, state = self._split(raw.gather(1, order[..., None, None].expand_as(raw)))  # split once for every peak
        m = m.gather(1, order[..., None])
        pos = torch.arange(t.shape[1], device=t.device)[None, :, None]  # (1, S, 1)
        left = conf.clone()  # (R, S, A): confidences still free to become a peak
        parts = []
        for _ in range(k):
            best = left.argmax(dim=1, keepdim=True)  # (R, 1, A)
            peak = left.gather(1, best)  # 0: every sample already taken
            above = conf >= PEAK_RUN * peak
            # "true at every sample so far" as no false one counted yet (cumsum: ONNX has no cumprod)
            after = (~(above | (pos < best))).to(torch.int32).cumsum(dim=1) == 0
            before = (~(above | (pos > best))).to(torch.int32).flip(1).cumsum(dim=1).flip(1) == 0
            run = (after & before).to(raw.dtype) * m  # (R, S, A)
            part = self._aggregate_windows(yolo, state, t, conf, run)
            part.ray_confidence = peak[:, 0]
            parts.append(part)
            at = t[..., None].expand_as(conf).gather(1, best)
            left = torch.where((run > 0) | ((t[..., None] - at).abs() < gap), torch.zeros_like(left), left)
        return RayOutputs(**{f: torch.stack([getattr(p, f) for p in parts], dim=2) for f in PER_RAY})

    def _aggregate_windows(self, yolo: Tensor, state: Tensor, t: Tensor, conf: Tensor, window: Tensor) -> RayOutputs:
        """``_aggregate`` of raw's YOLO values and state (``_split``) with a per-anchor window (R, S, A) of the
        samples that take part."""
        w = (conf + self.eps) * window
        w = w / w.sum(dim=1, keepdim=True).clamp_min(1e-12)
        values = torch.einsum("rsac,rsa->rac", yolo[..., 1:], w)
        return RayOutputs((conf * window).max(dim=1).values, values[..., :4], values[..., 4:],
                          (t[..., None] * w).sum(1), state=torch.einsum("rsac,rsa->rac", state, w))
