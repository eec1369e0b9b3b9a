"""Attention along the ray (the paper's future work): a small transformer over each ray's samples
that sets how much each sample counts in the ray's box, class and distance, instead of its
confidence alone (``model.aggregator: transformer``).

    agg = RayTransformer(num_anchors=3, d_sample=3 * 7)
    w = agg(raw, t, conf, m)      # (R, S, A) weights, 0 on invalid samples, summing to 1 per ray and anchor

Each sample's input is its MLP outputs for every anchor plus a sinusoidal encoding of its distance
along the ray; 1-2 encoder layers let every sample see the others (an occluder in front of a road
user, two road users on one ray); a linear head adds a learned logit per anchor to the log of the
sample's confidence. The head starts at zero, so training starts from the paper's confidence-weighted
mean exactly; the ray's confidence stays the maximum over its samples and the depth peaks are kept.
"""
from __future__ import annotations

from dataclasses import dataclass

import math

import torch
from torch import Tensor, nn


@dataclass
class AggregatorConfig:
    kind: str = "weighted_mean"  # weighted_mean (the paper's) | transformer (attention along the ray)
    width: int = 32  # transformer: the samples' width
    layers: int = 1  # transformer: encoder layers
    heads: int = 4  # transformer: attention heads (a divisor of width)


def depth_encoding(t: Tensor, width: int, scale_m: float = 50.0) -> Tensor:
    """(R, S) metres -> (R, S, width) sines and cosines of t / scale at octave frequencies."""
    freqs = torch.exp2(torch.arange(width // 2, device=t.device, dtype=t.dtype)) * math.pi / scale_m
    angles = t[..., None] * freqs
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1)


class RayTransformer(nn.Module):
    def __init__(self, num_anchors: int, d_sample: int, width: int = 32, layers: int = 1, heads: int = 4,
                 eps: float = 1e-5):
        super().__init__()
        self.width, self.eps = width, eps
        self.lin_in = nn.Linear(d_sample, width)
        layer = nn.TransformerEncoderLayer(width, heads, dim_feedforward=2 * width, dropout=0.0, batch_first=True)
        self.encoder = nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        self.head = nn.Linear(width, num_anchors)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, raw: Tensor, t: Tensor, conf: Tensor, m: Tensor) -> Tensor:
        """raw (R, S, A, 5 + C), t (R, S), conf (R, S, A) (0 on invalid samples), m (R, S, 1) valid
        -> (R, S, A) aggregation weights."""
        R, S = t.shape
        pad = m[..., 0] <= 0
        empty = pad.all(dim=1, keepdim=True)  # a ray without valid samples attends to all (weights zeroed below)
        x = self.lin_in(raw.reshape(R, S, -1)) + depth_encoding(t, self.width)
        z = self.encoder(x, src_key_padding_mask=pad & ~empty)
        logits = torch.log(conf + self.eps) + self.head(z)
        logits = logits.masked_fill(pad[..., None], float("-inf"))
        return torch.nan_to_num(torch.softmax(logits, dim=1), nan=0.0) * m
