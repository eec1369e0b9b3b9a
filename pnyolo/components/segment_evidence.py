"""Where along a frustum segment the source views agree (issue 89): the evidence that tells a hidden road user from
its occluder when both lie in one coarse segment.

A segment (``t`` +- ``half`` along its ray) is split into ``m`` sub-points at the middles of ``m`` equal parts. Each
sub-point is read in every source view that sees it; where the views agree about it (the spread of their features
around their mean is small) a surface all of them see lies there, as in multi-view stereo's cost volumes and
pixelNeRF's variance across views; where one view sees an occluder in front of it, they do not. A softmax over the
sub-points by that agreement says where in the segment the views meet. The segment's evidence is what the views see
there (each view's features averaged with those weights: mip-NeRF's mean over the volume, not its maximum), how
strongly they agree at best, and where (the expected offset in the segment, -1 near to +1 far)::

    t_sub = sub_points(t, half, m)                      # (..., m) metres along the ray
    ev = segment_evidence(feats, valid)                 # feats (V, N, m, C), valid (V, N, m) -> SegmentEvidence
    ev.weights                                          # (N, m) where along each segment the views agree
    ev.offset, ev.agreement, ev.features                # (N,), (N,), (V, N, C)
    ev, seen = read_segments(frustums, cameras, maps, strides, m)      # a model's segments (n, S)

pixelNeRF-YOLO reads it with ``model.sampler.footprint: evidence``: each coarse sample's MLP input is every view's
features where the views agree in its segment, with the offset and agreement as inputs of their own, and the fine
samples are drawn from the coarse confidence times where in each bin the views agree.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from pnyolo.components.encoder import index_features

NO_AGREEMENT = -4.0  # a sub-point fewer than two views see: nothing to agree about (log-scale floor)


@dataclass(frozen=True)
class SegmentEvidence:
    weights: Tensor  # (N, m) softmax over the sub-points by agreement
    scores: Tensor  # (N, m) each sub-point's agreement (``agreement``)
    offset: Tensor  # (N,) expected position in the segment, -1 (near end) .. +1 (far end)
    agreement: Tensor  # (N,) the best sub-point's agreement (log scale; NO_AGREEMENT: no two views)
    features: Tensor  # (V, N, C) each view's features averaged over the sub-points by ``weights``


def sub_offsets(m: int, device=None, dtype=torch.float32) -> Tensor:
    """(m,) the middles of m equal parts of [-1, 1]."""
    return (2 * torch.arange(m, device=device, dtype=dtype) + 1) / m - 1


def sub_points(t: Tensor, half: Tensor, m: int) -> Tensor:
    """Distances (..., m) of the ``m`` sub-points of segments ``t`` +- ``half`` (...)."""
    return t[..., None] + half[..., None] * sub_offsets(m, t.device, t.dtype)


def agreement(feats: Tensor, valid: Tensor) -> Tensor:
    """(N, m) how alike the views that see each sub-point are: minus the log of their features' mean squared spread
    around their mean, per channel (NO_AGREEMENT where fewer than two views see it). ``feats`` (V, N, m, C), ``valid``
    (V, N, m) bool."""
    w = valid.to(feats.dtype)[..., None]  # (V, N, m, 1)
    count = w.sum(0)  # (N, m, 1)
    seen = feats * w  # the only products over every view and channel: this sum is most of the evidence's cost
    total, squares = seen.sum(0), (seen * feats).sum(0)  # (N, m, C)
    # the spread around the mean, sum w (f - mean)^2 = sum w f^2 - mean sum w f, relative to the features' size
    # (unit-free); both sums over the same views, so no count divides them
    spread = (squares - total * (total / count.clamp_min(1))).clamp_min(0).mean(-1)
    scale = squares.mean(-1)
    score = -torch.log(spread / scale.clamp_min(1e-12) + 1e-6)
    return torch.where(count[..., 0] >= 2, score, torch.full_like(score, NO_AGREEMENT))


def segment_evidence(feats: Tensor, valid: Tensor, sharpness: float = 1.0, own: Tensor | None = None
                     ) -> SegmentEvidence:
    """The evidence (module docstring) of N segments from their sub-points' features in V views (V, N, m, C) and
    whether each view sees each sub-point (V, N, m); ``sharpness`` scales the agreement before the softmax. ``own``
    (V, N) bool: each segment's own view (its ray's), left out of the agreement: it sees the ray's one pixel at every
    sub-point, so it says nothing of where along the ray (and for a road user hidden there, it sees the occluder)."""
    score = agreement(feats, valid if own is None else valid & ~own[..., None])  # (N, m)
    weights = torch.softmax(sharpness * score, dim=-1)
    m = feats.shape[2]
    offset = (weights * sub_offsets(m, feats.device, feats.dtype)).sum(-1)
    seen = valid.to(feats.dtype) * weights[None]  # (V, N, m): one product over the channels below
    averaged = (feats * seen[..., None]).sum(2)  # (V, N, C): what each view sees where they agree
    return SegmentEvidence(weights, score, offset, score.max(dim=-1).values, averaged)


def read_segments(segments, cameras, maps: list[Tensor], strides: list[int], m: int,
                  own: Tensor | None = None) -> tuple[SegmentEvidence, Tensor]:
    """The evidence of ``segments`` (``frustums.Frustums``: rays (n), segments t +- half (n, S)) in every view of
    ``cameras`` (``geometry.Cameras``), read from ``maps`` at ``m`` sub-points each, each ray's ``own`` view (V, n)
    left out of the agreement; and whether each view sees any of a segment's sub-points (V, n, S)."""
    n, S = segments.t.shape
    ts = sub_points(segments.t, segments.half, m)  # (n, S, m)
    points = segments.origins[:, None, None] + ts[..., None] * segments.dirs[:, None, None]
    uv, _, _, valid = cameras.project(points)  # (V, n, S, m, ...)
    V = uv.shape[0]
    feats = index_features(maps, uv.reshape(V, n * S * m, 2), strides).reshape(V, n * S, m, -1)
    own = None if own is None else own[:, :, None].expand(V, n, S).reshape(V, n * S)
    ev = segment_evidence(feats, valid.reshape(V, n * S, m), own=own)
    return ev, valid.any(dim=-1)
