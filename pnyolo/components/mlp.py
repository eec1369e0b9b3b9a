"""The NeRF MLP with a YOLO output: ResNet-style FC blocks, per-view blocks, one combine step.

Per (point, source view) the input is ``[PE(x_view), d_view, valid, is_target]`` (the point and
the ray direction in that view's camera axes, whether the point projects into the view, and
whether this view is the ray's *target* view: the one whose grid cell the ray goes through) plus
the view's image features (zero when not valid), added into every per-view block.

``is_target`` (``MLPConfig.target_view_flag``) is a deviation from the paper. The box values
(x, y in the target cell, w, h as fractions of the target image) and the cell's objectness are
properties of the target view, but after a symmetric combine (mean) the MLP cannot tell which
of the V source views that is: the same 3D point sampled on rays of different views gets the
same pooled feature and must output different boxes. (The original code got such a cue by
accident: its rays pointed away from the scene in their own view, so the target view was the
one with zeroed features.) The toy-scene overfit learns faster with it.
``target=None`` means "no view is the target" (e.g. a query point not on any view's grid ray). After
``combine_layer`` blocks the views are combined by ``COMBINE_FUNCTIONS[combine]`` (the paper:
mean; ``mean_var`` adds the variance over the views), then the remaining blocks and a linear layer
give ``anchors x (5 + classes)`` raw values ``(obj, tx, ty, tw, th, class logits...)``, followed, with ``state``,
by each anchor's 3D state from a linear layer of its own (``pnyolo.components.view_state``).

Example::

    mlp = YoloMLP(d_latent=512, num_anchors=3, num_classes=2, cfg=MLPConfig())
    raw = mlp(x_view, d_view, valid, feats, target)  # (V, N, ...) -> (N, A, 5 + C)
"""
from __future__ import annotations

from dataclasses import dataclass

import math
from typing import Callable

import torch
from torch import Tensor, nn

from dataset_spec.cli_support import UserError


@dataclass
class MLPConfig:
    hidden: int = 512  # width of the MLP's residual blocks
    num_blocks: int = 5  # residual blocks
    combine_layer: int = 3  # blocks before the combine step run per view
    combine: str = "mean"  # mean | max | mean_var (pnyolo.components.mlp.COMBINE_FUNCTIONS) | attention
    attention_heads: int = 4  # combine: attention: heads across the views (a divisor of hidden)
    pe_frequencies: int = 6  # positional encoding of a point: sines and cosines at this many frequencies
    pe_factor: float = 1.5  # frequency k is pe_factor^k * pi
    include_raw_input: bool = True  # the point's coordinates also enter the MLP unencoded
    use_view_dirs: bool = True  # the ray direction in each view's camera frame is an MLP input
    target_view_flag: bool = True  # per-view input "this view is the ray's target view" (not in the paper)


class PositionalEncoding(nn.Module):
    """NeRF encoding: [x, sin(f_k x), cos(f_k x)] with f_k = factor^k * pi, k < num_freqs."""

    def __init__(self, num_freqs: int = 6, factor: float = 1.5, include_input: bool = True, d_in: int = 3):
        super().__init__()
        self.include_input = include_input
        self.register_buffer("freqs", factor ** torch.arange(num_freqs, dtype=torch.float32) * math.pi,
                             persistent=False)
        self.d_out = d_in * 2 * num_freqs + (d_in if include_input else 0)

    def forward(self, x: Tensor) -> Tensor:  # (..., d) -> (..., d_out)
        xf = (x[..., None] * self.freqs).flatten(-2)
        parts = [torch.sin(xf), torch.cos(xf)]
        if self.include_input:
            parts.insert(0, x)
        return torch.cat(parts, dim=-1)


class ResnetBlockFC(nn.Module):
    """x + fc_1(relu(fc_0(relu(x))))."""

    def __init__(self, size: int):
        super().__init__()
        self.fc_0 = nn.Linear(size, size)
        self.fc_1 = nn.Linear(size, size)
        self.act = nn.ReLU()
        nn.init.kaiming_normal_(self.fc_0.weight, a=0, mode="fan_in")
        nn.init.zeros_(self.fc_0.bias)
        nn.init.zeros_(self.fc_1.weight)
        nn.init.zeros_(self.fc_1.bias)

    def forward(self, x: Tensor) -> Tensor:  # (..., size) -> (..., size)
        return x + self.fc_1(self.act(self.fc_0(self.act(x))))


def mean_combine(x: Tensor) -> Tensor:
    """Combine per-view activations (V, N, H) -> (N, H) by the mean (the paper's choice)."""
    return x.mean(dim=0)


def max_combine(x: Tensor) -> Tensor:
    """(V, N, H) -> (N, H): the maximum over the views."""
    return x.max(dim=0).values


def mean_var_combine(x: Tensor) -> Tensor:
    """(V, N, H) -> (N, 2H): the mean and the (population) variance over the views, as IBRNet pools
    its source views: the variance says whether the views agree about a point (a surface all of them
    see) or not (a point one view sees and another sees an occluder in front of)."""
    var, mean = torch.var_mean(x, dim=0, unbiased=False)
    return torch.cat([mean, var], dim=-1)


COMBINE_FUNCTIONS: dict[str, Callable[[Tensor], Tensor]] = {"mean": mean_combine, "max": max_combine,
                                                            "mean_var": mean_var_combine}
ATTENTION = "attention"  # learned attention across the views (AttentionCombine): a combine with parameters
COMBINES = (*COMBINE_FUNCTIONS, ATTENTION)
# How many times the hidden width a combine returns; a wider one is mapped back by a learned linear
# layer that starts as "take the mean" (the paper's combine), so training begins from the paper's model.
COMBINE_WIDTH = {"mean_var": 2}


class AttentionCombine(nn.Module):
    """Attention across the source views at the combine layer: per point and head, a query (a learned
    vector plus the point's target-view activation, where it has a target view) scores each view's
    activation; a view the point does not project into gets no weight (no view: a zero output), and
    the weighted views' activations are summed. The key projection starts at zero, so training begins
    from the mean over the views that see the point. Invariant to the order of the source views."""

    def __init__(self, hidden: int, heads: int):
        super().__init__()
        if hidden % heads:
            raise ValueError(f"hidden width {hidden} is not a multiple of {heads} heads")
        self.heads = heads
        self.query = nn.Parameter(torch.zeros(hidden))
        self.lin_q = nn.Linear(hidden, hidden)
        self.lin_k = nn.Linear(hidden, hidden)
        nn.init.zeros_(self.lin_k.weight)
        nn.init.zeros_(self.lin_k.bias)

    def weights(self, h: Tensor, valid: Tensor, target: Tensor | None) -> Tensor:
        """(V, N, H) activations, (V, N) valid, (V, N) target -> (V, N, heads) weights (0 where not valid)."""
        V, N, H = h.shape
        d = H // self.heads
        own = torch.zeros_like(h[0]) if target is None else (h * target.to(h.dtype)[..., None]).sum(0)
        q = (self.query + self.lin_q(own)).view(N, self.heads, d)
        k = self.lin_k(h).view(V, N, self.heads, d)
        scores = (k * q[None]).sum(-1) / d ** 0.5  # (V, N, heads)
        scores = scores.masked_fill(~valid[..., None], float("-inf"))
        w = torch.softmax(scores, dim=0)
        return torch.nan_to_num(w, nan=0.0)  # a point no view sees: every weight 0

    def forward(self, h: Tensor, valid: Tensor, target: Tensor | None) -> Tensor:  # (V, N, H) -> (N, H)
        V, N, H = h.shape
        w = self.weights(h, valid, target)
        return (w[..., None] * h.view(V, N, self.heads, H // self.heads)).sum(0).reshape(N, H)


class YoloMLP(nn.Module):
    def __init__(self, d_latent: int, num_anchors: int, num_classes: int, cfg: MLPConfig, obj_bias_init: float = -4.0,
                 d_point: int = 0, state: int = 0):
        super().__init__()
        if cfg.combine not in COMBINES:
            raise UserError(f"config model.mlp.combine: {cfg.combine!r} ({' | '.join(COMBINES)})")
        self.cfg = cfg
        self.num_anchors, self.num_classes = num_anchors, num_classes
        self.combine = COMBINE_FUNCTIONS.get(cfg.combine)
        self.attention = AttentionCombine(cfg.hidden, cfg.attention_heads) if cfg.combine == ATTENTION else None
        self.pe = PositionalEncoding(cfg.pe_frequencies, cfg.pe_factor, cfg.include_raw_input)
        self.d_point = d_point  # per-point inputs shared by every view (e.g. the sample's bin half-width)
        d_in = self.pe.d_out + (3 if cfg.use_view_dirs else 0) + 1 + (1 if cfg.target_view_flag else 0) + d_point
        self.lin_in = nn.Linear(d_in, cfg.hidden)
        self.lin_z = nn.ModuleList([nn.Linear(d_latent, cfg.hidden) for _ in range(cfg.combine_layer)])
        self.blocks = nn.ModuleList([ResnetBlockFC(cfg.hidden) for _ in range(cfg.num_blocks)])
        width = COMBINE_WIDTH.get(cfg.combine, 1)
        self.lin_combine = None
        if width > 1:
            self.lin_combine = nn.Linear(width * cfg.hidden, cfg.hidden)
            with torch.no_grad():
                self.lin_combine.weight.zero_()
                self.lin_combine.weight[:, :cfg.hidden] = torch.eye(cfg.hidden)
                self.lin_combine.bias.zero_()
        self.lin_out = nn.Linear(cfg.hidden, num_anchors * (5 + num_classes))
        self.act = nn.ReLU()
        for lin in [self.lin_in, *self.lin_z]:
            nn.init.kaiming_normal_(lin.weight, a=0, mode="fan_in")
            nn.init.zeros_(lin.bias)
        with torch.no_grad():
            nn.init.normal_(self.lin_out.weight, std=1e-3)
            bias = self.lin_out.bias.view(num_anchors, 5 + num_classes)
            bias.zero_()
            bias[:, 0] = obj_bias_init
        # Each anchor's 3D state (``state`` values, pnyolo.components.view_state) from a layer of its own, made after
        # every other one: the YOLO values' initial weights are those of an MLP without it.
        self.state = state
        self.lin_state = nn.Linear(cfg.hidden, num_anchors * state) if state else None
        if self.lin_state is not None:
            with torch.no_grad():
                nn.init.normal_(self.lin_state.weight, std=1e-3)
                self.lin_state.bias.zero_()

    def forward(self, x_view: Tensor, d_view: Tensor, valid: Tensor, feats: Tensor,
                target: Tensor | None = None, point: Tensor | None = None) -> Tensor:
        """
        Args:
            x_view: (V, N, 3) points in each source view's camera axes.
            d_view: (V, N, 3) unit ray directions in each view's camera axes.
            valid: (V, N) bool, the point projects into the view (in image, in front).
            feats: (V, N, d_latent) indexed image features.
            target: (V, N) bool, the view is the point's target view (None: no view is).
            point: (N, d_point) per-point inputs, the same for every view (``d_point`` > 0 only).
        Returns:
            (N, A, 5 + C + state) raw outputs.
        """
        vf = valid.to(x_view.dtype)[..., None]
        parts = [self.pe(x_view)]
        if self.cfg.use_view_dirs:
            parts.append(d_view)
        parts.append(vf)
        if self.cfg.target_view_flag:
            parts.append(torch.zeros_like(vf) if target is None else target.to(vf.dtype)[..., None])
        if self.d_point:
            parts.append(point[None].expand(x_view.shape[0], *point.shape))
        z = feats * vf
        h = self.lin_in(torch.cat(parts, dim=-1))
        for i, block in enumerate(self.blocks):
            if i == self.cfg.combine_layer:
                h = self._combine(h, valid, target)
            if i < self.cfg.combine_layer:
                h = h + self.lin_z[i](z)
            h = block(h)
        if self.cfg.combine_layer == len(self.blocks):
            h = self._combine(h, valid, target)
        h = self.act(h)
        out = self.lin_out(h)
        out = out.view(*out.shape[:-1], self.num_anchors, 5 + self.num_classes)
        if self.lin_state is None:
            return out
        state = self.lin_state(h)
        return torch.cat([out, state.view(*state.shape[:-1], self.num_anchors, self.state)], dim=-1)

    def _combine(self, h: Tensor, valid: Tensor, target: Tensor | None) -> Tensor:
        """Per-view activations (V, N, H) -> (N, H)."""
        if self.attention is not None:
            return self.attention(h, valid, target)
        h = self.combine(h)
        return h if self.lin_combine is None else self.lin_combine(h)
