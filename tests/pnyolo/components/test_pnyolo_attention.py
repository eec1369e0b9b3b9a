"""Attention across the source views (model.mlp.combine: attention): shapes, masking, order
invariance, and a start from the mean over the views that see the point."""
from __future__ import annotations

import torch

from pnyolo.components.mlp import AttentionCombine, YoloMLP
from pnyolo.components.mlp import MLPConfig

torch.manual_seed(0)


def _trained_like(att: AttentionCombine) -> AttentionCombine:
    with torch.no_grad():  # weights away from their start, as after training
        for p in att.parameters():
            p.normal_(0, 0.5)
    return att


def test_attention_starts_as_the_mean_over_the_views_that_see_the_point():
    att = AttentionCombine(8, heads=2)
    h = torch.randn(3, 5, 8)
    valid = torch.tensor([[True, True, False, True, False]] * 2 + [[True, False, False, True, False]])
    out = att(h, valid, None)
    for n in range(5):
        seen = valid[:, n]
        expected = h[seen, n].mean(0) if seen.any() else torch.zeros(8)
        assert torch.allclose(out[n], expected, atol=1e-6)


def test_a_view_that_does_not_see_the_point_gets_no_weight():
    att = _trained_like(AttentionCombine(8, heads=4))
    h = torch.randn(3, 6, 8)
    valid = torch.ones(3, 6, dtype=torch.bool)
    valid[1, :3] = False
    target = torch.zeros(3, 6, dtype=torch.bool)
    target[0] = True
    w = att.weights(h, valid, target)
    assert torch.all(w[1, :3] == 0) and torch.allclose(w.sum(0), torch.ones(6, 4), atol=1e-6)
    changed = h.clone()
    changed[1] += 10.0  # view 1 changes everywhere: where it is blind, nothing follows
    assert torch.allclose(att(changed, valid, target)[:3], att(h, valid, target)[:3], atol=1e-6)
    assert not torch.allclose(att(changed, valid, target)[3:], att(h, valid, target)[3:])


def test_the_order_of_the_source_views_does_not_matter():
    cfg = MLPConfig(hidden=16, num_blocks=3, combine_layer=2, combine="attention", attention_heads=4)
    mlp = YoloMLP(24, 3, 2, cfg).eval()
    _trained_like(mlp.attention)
    V, N = 3, 7
    x, d = torch.randn(V, N, 3), torch.nn.functional.normalize(torch.randn(V, N, 3), dim=-1)
    valid = torch.rand(V, N) > 0.3
    feats, target = torch.randn(V, N, 24), torch.zeros(V, N, dtype=torch.bool)
    target[1] = True
    out = mlp(x, d, valid, feats, target)
    assert out.shape == (N, 3, 7)
    perm = torch.tensor([2, 0, 1])
    again = mlp(x[perm], d[perm], valid[perm], feats[perm], target[perm])
    assert torch.allclose(out, again, atol=1e-5)


def test_the_ray_transformer_starts_as_the_papers_weighted_mean_and_ignores_invalid_samples():
    from pnyolo.components.ray_attention import RayTransformer
    from pnyolo.components.renderer import YoloRayRenderer

    R, S, A, C = 5, 12, 3, 2
    raw, t = torch.randn(R, S, A, 5 + C), torch.rand(R, S) * 40
    valid = torch.rand(R, S) > 0.25
    valid[0] = False  # a ray without valid samples
    plain = YoloRayRenderer()(raw, t, valid)
    att = RayTransformer(A, A * (5 + C), width=16, layers=2, heads=4)
    start = YoloRayRenderer(attention=att)(raw, t, valid)
    for f in ("ray_confidence", "box", "class_logits", "depth"):
        assert torch.allclose(getattr(start, f), getattr(plain, f), atol=1e-5), f
    _trained_like(att)
    m = valid.float()[..., None]
    conf = torch.sigmoid(raw[..., 0]) * m
    w = att(raw, t, conf, m)
    assert torch.all(w[~valid] == 0) and torch.all(w[0] == 0)
    assert torch.allclose(w[1:].sum(1), torch.ones(R - 1, A), atol=1e-5)
    changed = raw.clone()
    changed[~valid] += 5.0  # what invalid samples hold does not reach the ray
    assert torch.allclose(att(changed, t, torch.sigmoid(changed[..., 0]) * m, m), w, atol=1e-5)
    trained = YoloRayRenderer(attention=att)(raw, t, valid, peaks=2)
    assert trained.peaks is not None and trained.peaks.ray_confidence.shape == (R, A, 2)  # depth peaks kept
    assert torch.equal(trained.ray_confidence, plain.ray_confidence)  # the ray's confidence: its best sample
