"""Targets, loss, renderer and the ray MLP on small hand-made inputs."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings, strategies as st

from dataset_spec.boxes import box_iou as np_box_iou, box_to_yolo, yolo_to_box as np_yolo_to_box
from pnyolo.components.boxes import box_iou, elementwise_iou_cxcywh, generalized_iou_cxcywh, yolo_to_box
from pnyolo.components.encoder import ResNetEncoder, index_features
from pnyolo.components.losses import YoloLoss
from pnyolo.components.mlp import COMBINE_FUNCTIONS, MLPConfig, YoloMLP
from pnyolo.components.renderer import YoloRayRenderer
from pnyolo.config.model import YoloLossConfig
from pnyolo.data.targets import TARGET_CHANNELS, build_targets, decode_boxes, perfect_raw
from pnyolo.evaluation.metrics import (MetricAccumulator, ViewDetections, ViewGroundTruth, average_precision,
                                       ignored_predictions)
from pnyolo.decoding.nms import nms

torch.set_num_threads(2)
ANCHORS = torch.tensor([[0.02, 0.03], [0.04, 0.07], [0.08, 0.06]])


def _gt(W=960, H=540):
    boxes = np.array([[100, 200, 130, 250], [500, 100, 580, 140], [700, 300, 712, 330], [505, 105, 540, 160]], float)
    return boxes, np.array([0, 1, 0, 1]), W, H


def test_targets_then_decode_returns_ground_truth_boxes():
    boxes, classes, W, H = _gt()
    yolo = torch.tensor(np.stack([box_to_yolo(b, W, H) for b in boxes]), dtype=torch.float32)
    target = build_targets(yolo, torch.tensor(classes), 18, 32, ANCHORS, 0.5)
    obj = target[..., 0] == 1
    assert int(obj.sum()) == len(boxes)
    raw = perfect_raw(target, ANCHORS, 2)
    dec = yolo_to_box(decode_boxes(raw["box"], ANCHORS)[obj], W, H).double().numpy()
    cls = raw["class_logits"][obj].argmax(-1).numpy()
    order = np.lexsort((dec[:, 1], dec[:, 0]))
    ref = np.lexsort((boxes[:, 1], boxes[:, 0]))
    np.testing.assert_allclose(dec[order], boxes[ref], atol=0.05)
    assert (cls[order] == classes[ref]).all()
    # the numpy contract agrees with the torch conversion
    np.testing.assert_allclose(np_yolo_to_box(yolo[0].double().numpy(), W, H), boxes[0], atol=1e-3)


def test_ignore_threshold_marks_similar_anchors():
    anchors = torch.tensor([[0.1, 0.1], [0.11, 0.11], [0.5, 0.5]])
    t = build_targets(torch.tensor([[0.5, 0.5, 0.1, 0.1]]), torch.tensor([0]), 4, 4, anchors, 0.5)
    assert t[2, 2, :, 0].tolist() == [1.0, -1.0, 0.0]


def test_box_hidden_behind_another_in_the_same_cell_gets_the_next_free_anchor():
    # A car and a slightly smaller one right behind it: same cell, same best anchor.
    anchors = torch.tensor([[0.02, 0.06], [0.1, 0.1], [0.3, 0.2]])
    boxes = torch.tensor([[0.52, 0.52, 0.11, 0.1], [0.53, 0.51, 0.09, 0.08]])
    t = build_targets(boxes, torch.tensor([1, 1]), 4, 4, anchors, 0.5)
    cell = t[2, 2]
    assert int((cell[:, 0] == 1).sum()) == 2  # both objects own a slot
    owned = sorted(cell[cell[:, 0] == 1][:, 3].tolist())
    assert owned == pytest.approx([0.09, 0.11])
    # the larger box (drawn first) keeps the best anchor; the smaller one takes its next-best, free one
    assert cell[1, 3] == pytest.approx(0.11) and cell[0, 3] == pytest.approx(0.09)
    # a perfect prediction of these targets decodes back to both boxes
    raw = perfect_raw(t, anchors, 2)
    dec = decode_boxes(raw["box"], anchors)[t[..., 0] == 1]
    np.testing.assert_allclose(sorted(dec[:, 2].tolist()), [0.09, 0.11], atol=1e-4)
    # without the fallback the larger box loses its slot (the old behaviour)
    old = build_targets(boxes, torch.tensor([1, 1]), 4, 4, anchors, 0.5, fallback=False)
    assert int((old[..., 0] == 1).sum()) == 1
    # more objects than anchors in one cell: every anchor is used, nothing crashes
    crowd = torch.tensor([[0.52, 0.52, 0.1 - 0.01 * k, 0.1] for k in range(5)])
    t5 = build_targets(crowd, torch.zeros(5, dtype=torch.long), 4, 4, anchors, 0.5)
    assert int((t5[2, 2, :, 0] == 1).sum()) == 3


def test_road_users_left_out_of_the_ground_truth_are_ignored_not_background():
    from pnyolo.data.targets import IGNORE, OBJ, ignore_regions

    anchors = torch.tensor([[0.1, 0.2], [0.3, 0.3]])
    kept = torch.tensor([[0.3125, 0.375, 0.1, 0.2]])  # a pedestrian in cell (1, 2) of a 4x8 grid
    t = build_targets(kept, torch.tensor([1]), 4, 8, anchors)
    # a big left-out truck over the left half, the pedestrian inside it; a far car; one outside the image
    left_out = torch.tensor([[0.25, 0.5, 0.5, 1.0], [0.8125, 0.125, 0.02, 0.02], [1.5, 0.5, 0.2, 0.2]])
    out = ignore_regions(t, left_out)
    truck = torch.zeros(4, 8, dtype=torch.bool)
    truck[:, :4] = True  # cells whose centres lie inside the truck's box
    far = torch.zeros(4, 8, dtype=torch.bool)
    far[0, 6] = True  # too small to hold a cell centre: the cell holding its centre
    ignored = (out[..., 0] == IGNORE).all(-1)
    obj = (out[..., 0] == OBJ).any(-1)
    assert torch.equal(ignored | obj, truck | far) and obj.sum() == 1 and out[1, 2, 0, 0] == OBJ
    assert out[1, 2, 1, 0] == IGNORE
    anchor_obj = t[..., 0] == OBJ  # the pedestrian's own anchor keeps its target; its cell's other one is ignored
    assert torch.equal(out[anchor_obj], t[anchor_obj]) and torch.equal(out[~(truck | far)], t[~(truck | far)])
    assert torch.equal(ignore_regions(t, left_out[2:]), t)  # a box wholly outside the image marks nothing
    # the loss sees no background where the truck is: predicting an object there costs nothing
    conf = torch.where(truck[..., None].expand(4, 8, 2), 0.99, 0.01)
    loss = YoloLoss(YoloLossConfig(box=0, obj=0, cls=0))
    box, cls = torch.zeros(4, 8, 2, 4), torch.zeros(4, 8, 2, 2)
    assert loss(conf, box, cls, out, anchors)[1]["noobj"] < 0.02 < loss(conf, box, cls, t, anchors)[1]["noobj"]


def test_loss_near_zero_for_perfect_prediction_and_positive_otherwise():
    boxes, classes, W, H = _gt()
    yolo = torch.tensor(np.stack([box_to_yolo(b, W, H) for b in boxes]), dtype=torch.float32)
    target = build_targets(yolo, torch.tensor(classes), 18, 32, ANCHORS, 0.5)
    raw = perfect_raw(target, ANCHORS, 2)
    loss_fn = YoloLoss()
    total, terms = loss_fn(raw["ray_confidence"], raw["box"], raw["class_logits"], target, ANCHORS)
    assert float(total) < 1e-3, terms
    worse, _ = loss_fn(raw["ray_confidence"] * 0.5, raw["box"] + 0.3, raw["class_logits"] * 0, target, ANCHORS)
    assert float(worse) > 0.1


def test_generalized_iou_on_hand_made_boxes():
    a = torch.tensor([0.5, 0.5, 0.2, 0.2])
    assert float(generalized_iou_cxcywh(a, a)) == pytest.approx(1.0)
    inside = torch.tensor([0.5, 0.5, 0.1, 0.1])  # hull = the larger box: GIoU = IoU = 1/4
    assert float(generalized_iou_cxcywh(a, inside)) == pytest.approx(0.25)
    assert float(elementwise_iou_cxcywh(a, inside)) == pytest.approx(0.25)
    apart = torch.tensor([0.9, 0.5, 0.2, 0.2])  # disjoint: IoU 0, hull 0.6 x 0.2, union 0.08
    assert float(generalized_iou_cxcywh(a, apart)) == pytest.approx(-(0.12 - 0.08) / 0.12)
    farther = torch.tensor([0.95, 0.5, 0.2, 0.2])
    assert float(generalized_iou_cxcywh(a, farther)) < float(generalized_iou_cxcywh(a, apart))


def test_overlap_term_is_zero_when_right_and_counts_offsets_relative_to_the_box():
    """model.loss.iou: 1 - GIoU of each object anchor's decoded box; absent by default. The same shift
    in cell units costs a narrow box more than a wide one (the coordinate MSE costs both alike),
    and a box that misses its object entirely still gets a gradient towards it."""
    def setup(w):
        target = build_targets(torch.tensor([[0.5 / 8 + 0.01, 0.5 / 6, w, 0.1]]), torch.tensor([0]), 6, 8,
                               torch.tensor([[w, 0.1]]))
        return target, perfect_raw(target, torch.tensor([[w, 0.1]]), 2)
    fn = YoloLoss(YoloLossConfig(iou=1.0))
    costs = {}
    for w in (0.02, 0.2):
        target, raw = setup(w)
        anchors = torch.tensor([[w, 0.1]])
        _, terms = fn(raw["ray_confidence"], raw["box"], raw["class_logits"], target, anchors)
        assert terms["iou"] < 1e-6
        shifted = raw["box"].clone()
        shifted[..., 0] += 1.0  # a shift of the x logit: the same few pixels for both boxes
        _, terms = fn(raw["ray_confidence"], shifted, raw["class_logits"], target, anchors)
        costs[w] = (terms["iou"], terms["box"])
    assert costs[0.02][0] > 3 * costs[0.2][0]
    assert costs[0.02][1] == pytest.approx(costs[0.2][1])
    target, raw = setup(0.02)
    box = raw["box"].clone()
    box[..., 0] -= 6.0  # far left of its cell: no overlap with the target
    box.requires_grad_(True)
    only_iou = YoloLoss(YoloLossConfig(box=0, obj=0, noobj=0, cls=0, iou=1.0))
    only_iou(raw["ray_confidence"], box, raw["class_logits"], target, torch.tensor([[0.02, 0.1]]))[0].backward()
    obj = target[..., 0] == 1
    assert float(box.grad[obj][0, 0]) < 0  # descending moves the box right, towards its object
    assert "iou" not in YoloLoss()(raw["ray_confidence"], raw["box"], raw["class_logits"], target,
                                   torch.tensor([[0.02, 0.1]]))[1]


def _extras(weights=None, distances=None, n: int = 4):
    """``build_targets``' per-box extras: weights (default 1), distances (default 0), no 3D rows."""
    return torch.stack([torch.ones(n) if weights is None else weights,
                        torch.zeros(n) if distances is None else distances, torch.zeros(n)], dim=1)


def test_distance_term_is_zero_when_right_absent_without_distances_and_moves_confidence_to_the_object():
    """model.loss.depth: Huber of the rendered distance against the target's, only where both exist; its
    gradient concentrates an anchor's confidence on the samples at its object's distance."""
    boxes, classes, W, H = _gt()
    yolo = torch.tensor(np.stack([box_to_yolo(b, W, H) for b in boxes]), dtype=torch.float32)
    dist = torch.tensor([6.0, 9.0, 12.0, 15.0])
    target = build_targets(yolo, torch.tensor(classes), 18, 32, ANCHORS, 0.5, extras=_extras(distances=dist))
    obj = target[..., 0] == 1
    assert sorted(target[obj][:, 7].tolist()) == dist.tolist()
    raw = perfect_raw(target, ANCHORS, 2)
    fn = YoloLoss(YoloLossConfig(depth=1.0))
    args = (raw["ray_confidence"], raw["box"], raw["class_logits"], target, ANCHORS)
    right = target[..., 7].clone()
    _, terms = fn(*args, right)
    assert terms["depth"] < 1e-9
    _, terms = fn(*args, right + 3.0)
    assert terms["depth"] == pytest.approx(2.5, abs=1e-5)  # Huber, delta 1: 3 - 0.5
    _, terms = fn(*args, torch.full_like(right, float("nan")))  # a model without distances
    assert terms["depth"] == 0
    _, terms = fn(*args, right + 3.0 * ~obj)  # wrong distances on cells without an object do not count
    assert terms["depth"] < 1e-9
    assert "depth" not in YoloLoss()(*args, right + 3.0)[1]  # off by default (the paper)

    # one ray, 12 samples from 2 to 24 m, an object at 6 m: descending the distance term alone
    # raises the confidence of the samples near 6 m above those far from it
    t = torch.linspace(2, 24, 12)[None]
    logits = torch.zeros(1, 12, 1, 7, requires_grad=True)
    one = torch.zeros(1, 1, 1, TARGET_CHANNELS)
    one[0, 0, 0, :8] = torch.tensor([1, 0.5, 0.5, 0.05, 0.05, 0, 1, 6.0])
    only_depth = YoloLoss(YoloLossConfig(box=0, obj=0, noobj=0, cls=0, depth=1.0))
    opt = torch.optim.SGD([logits], lr=1.0)
    for _ in range(200):
        out = YoloRayRenderer()(logits, t, torch.ones(1, 12, dtype=torch.bool))
        loss, _ = only_depth(out.ray_confidence.reshape(1, 1, 1), out.box.reshape(1, 1, 1, 4),
                             out.class_logits.reshape(1, 1, 1, 2), one, ANCHORS[:1], out.depth.reshape(1, 1, 1))
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert abs(float(out.depth.detach()) - 6.0) < 0.5
    conf = torch.sigmoid(logits[0, :, 0, 0]).detach()
    near = (t[0] - 6.0).abs() < 4.5
    assert conf[near].mean() > 2 * conf[~near].mean()


def test_bce_object_loss_pushes_a_confidently_missed_object_harder_than_mse():
    boxes, classes, W, H = _gt()
    yolo = torch.tensor(np.stack([box_to_yolo(b, W, H) for b in boxes]), dtype=torch.float32)
    target = build_targets(yolo, torch.tensor(classes), 18, 32, ANCHORS, 0.5)
    raw = perfect_raw(target, ANCHORS, 2)
    obj = target[..., 0] == 1
    grads = {}
    for kind in ("mse", "bce"):
        fn = YoloLoss(YoloLossConfig(box=0, obj=1, noobj=0, cls=0, obj_target="one", obj_loss=kind))
        perfect, _ = fn(raw["ray_confidence"], raw["box"], raw["class_logits"], target, ANCHORS)
        assert float(perfect) < 1e-3, kind
        logit = torch.full(target.shape[:-1], -4.0, requires_grad=True)  # every object missed at p = 0.018
        total, _ = fn(torch.sigmoid(logit), raw["box"], raw["class_logits"], target, ANCHORS)
        total.backward()
        grads[kind] = float(logit.grad[obj].abs().mean())
        assert float(logit.grad[obj].max()) < 0  # both raise the object's confidence
    assert grads["bce"] > 20 * grads["mse"]  # (p - 1) versus 2 (p - 1) p (1 - p) on the logit


def test_object_weights_scale_its_loss_terms_and_zero_ignores_it():
    """The weight channel: all-ones is the unweighted loss; an object of weight 0 is in no term (its
    prediction can be anything); weight 2 doubles what a wrong prediction of it adds to each term."""
    boxes, classes, W, H = _gt()
    yolo = torch.tensor(np.stack([box_to_yolo(b, W, H) for b in boxes]), dtype=torch.float32)
    plain = build_targets(yolo, torch.tensor(classes), 18, 32, ANCHORS, 0.5)
    ones = build_targets(yolo, torch.tensor(classes), 18, 32, ANCHORS, 0.5, extras=_extras(weights=torch.ones(4)))
    torch.testing.assert_close(plain, ones)
    raw = perfect_raw(plain, ANCHORS, 2)
    fn = YoloLoss()

    def added_by_missing(k: int, weight: float) -> dict[str, float]:
        """Each term's increase when object k is predicted wrong (low confidence, shifted box, wrong class)."""
        w = torch.ones(4)
        w[k] = weight
        target = build_targets(yolo, torch.tensor(classes), 18, 32, ANCHORS, 0.5, extras=_extras(weights=w))
        row, col = int(float(yolo[k, 1]) * 18), int(float(yolo[k, 0]) * 32)  # object k's cell, alone in it
        slot = torch.zeros(target.shape[:-1], dtype=torch.bool)
        slot[row, col] = target[row, col, :, 0] == 1
        assert int(slot.sum()) == 1 and float(target[slot][0, 6]) == weight
        conf, box, logits = raw["ray_confidence"].clone(), raw["box"].clone(), raw["class_logits"].clone()
        conf[slot], box[slot] = 0.1, box[slot] + 0.5
        logits[slot] = logits[slot].flip(-1)
        _, good = fn(raw["ray_confidence"], raw["box"], raw["class_logits"], target, ANCHORS)
        _, bad = fn(conf, box, logits, target, ANCHORS)
        return {t: float(bad[t] - good[t]) for t in ("obj", "box", "cls")}

    one, two, zero = (added_by_missing(2, w) for w in (1.0, 2.0, 0.0))
    for term in ("obj", "box", "cls"):
        assert one[term] > 1e-3, (term, one)
        assert two[term] == pytest.approx(2 * one[term], rel=1e-4), term
        assert abs(zero[term]) < 1e-6, (term, zero)


def test_object_loss_weights_by_visibility_and_other_views():
    from pnyolo.data.targets import object_loss_weights

    vis = [0.0, 0.0, 0.3, 1.0, 0.0]
    seen = [True, False, False, True, True]
    w = object_loss_weights(vis, seen, YoloLossConfig(hidden_weight=3.0, unseen_weight=0.0))
    assert w.tolist() == [3.0, 0.0, 1.0, 1.0, 3.0]
    assert object_loss_weights(vis, seen, YoloLossConfig()).tolist() == [1.0] * 5  # the paper: all alike
    assert object_loss_weights([], [], YoloLossConfig(hidden_weight=2.0)).shape == (0,)


def _mlp_and_raw(n_rays=6, S=8, V=3, C=2, zero_conf=False):
    torch.manual_seed(0)
    mlp = YoloMLP(20, 3, C, MLPConfig(hidden=32, num_blocks=3, combine_layer=2))
    x = torch.randn(V, n_rays * S, 3, requires_grad=True)
    d = torch.nn.functional.normalize(torch.randn(V, n_rays * S, 3), dim=-1)
    valid = torch.rand(V, n_rays * S) > 0.3
    feats = torch.randn(V, n_rays * S, 20, requires_grad=True)
    raw = mlp(x, d, valid, feats).reshape(n_rays, S, 3, 5 + C)
    if zero_conf:
        raw = torch.cat([torch.full_like(raw[..., :1], -1e4), raw[..., 1:]], -1)
    return mlp, raw, (x, feats)


def test_renderer_and_loss_gradients_are_finite_everywhere():
    mlp, raw, inputs = _mlp_and_raw()
    t = torch.linspace(1, 13, 8).expand(6, 8)
    out = YoloRayRenderer()(raw, t, torch.ones(6, 8, dtype=torch.bool))
    target = torch.zeros(2, 3, 3, TARGET_CHANNELS)
    target[0, 1, 2, :8] = torch.tensor([1, 0.3, 0.6, 0.05, 0.05, 1, 1, 7.0])
    loss, terms = YoloLoss(YoloLossConfig(depth=1.0))(out.ray_confidence.reshape(2, 3, 3), out.box.reshape(2, 3, 3, 4),
                                                  out.class_logits.reshape(2, 3, 3, 2), target, ANCHORS,
                                                  out.depth.reshape(2, 3, 3))
    assert terms["depth"] > 0
    loss.backward()
    grads = [p.grad for p in mlp.parameters()] + [i.grad for i in inputs]
    assert all(gr is not None and torch.isfinite(gr).all() for gr in grads)
    assert ((out.depth >= 1) & (out.depth <= 13)).all()


def test_renderer_finite_with_vanishing_confidence_and_empty_rays():
    _, raw, _ = _mlp_and_raw(zero_conf=True)
    raw = raw.detach().requires_grad_(True)
    t = torch.linspace(1, 13, 8).expand(6, 8)
    valid = torch.ones(6, 8, dtype=torch.bool)
    valid[0] = False  # a ray that never enters the slab
    out = YoloRayRenderer()(raw, t, valid)
    for v in (out.ray_confidence, out.box, out.class_logits, out.depth):
        assert torch.isfinite(v).all()
    assert float(out.ray_confidence.detach().max()) == 0.0
    (out.box.sum() + out.depth.sum() + out.ray_confidence.sum()).backward()
    assert torch.isfinite(raw.grad).all()


def test_renderer_values_follow_the_confident_sample():
    raw = torch.zeros(1, 4, 1, 7)
    raw[..., 0] = -20.0
    raw[0, 2, 0, 0] = 20.0
    raw[0, 2, 0, 1:5] = torch.tensor([1.0, 2.0, 3.0, 4.0])
    t = torch.tensor([[2.0, 4.0, 6.0, 8.0]])
    out = YoloRayRenderer()(raw, t, torch.ones(1, 4, dtype=torch.bool))
    assert float(out.ray_confidence) == pytest.approx(1.0)
    np.testing.assert_allclose(out.box[0, 0].numpy(), [1, 2, 3, 4], atol=1e-3)
    assert float(out.depth) == pytest.approx(6.0, abs=1e-3)


def test_combine_is_a_single_swappable_function():
    x = torch.randn(3, 5, 4)
    assert torch.allclose(COMBINE_FUNCTIONS["mean"](x), x.mean(0))
    both = COMBINE_FUNCTIONS["mean_var"](x)
    assert both.shape == (5, 8)
    torch.testing.assert_close(both[:, 4:], ((x - x.mean(0)) ** 2).mean(0))  # population variance
    assert float(COMBINE_FUNCTIONS["mean_var"](x[:1].expand(3, 5, 4))[:, 4:].abs().max()) == 0  # views agree


def test_mean_var_combine_starts_as_the_mean_and_learns_from_the_variance():
    torch.manual_seed(0)
    cfgs = {c: MLPConfig(hidden=32, num_blocks=3, combine_layer=2, combine=c) for c in ("mean", "mean_var")}
    mlps = {c: YoloMLP(20, 3, 2, cfg) for c, cfg in cfgs.items()}
    mlps["mean_var"].load_state_dict(mlps["mean"].state_dict(), strict=False)  # all but lin_combine
    x, d = torch.randn(3, 40, 3), torch.nn.functional.normalize(torch.randn(3, 40, 3), dim=-1)
    valid, feats = torch.rand(3, 40) > 0.3, torch.randn(3, 40, 20)
    with torch.no_grad():
        torch.nn.init.normal_(mlps["mean"].lin_out.weight, std=0.1)
        mlps["mean_var"].lin_out.weight.copy_(mlps["mean"].lin_out.weight)
    torch.testing.assert_close(mlps["mean_var"](x, d, valid, feats), mlps["mean"](x, d, valid, feats))
    mlps["mean_var"](x, d, valid, feats).square().sum().backward()
    grad = mlps["mean_var"].lin_combine.weight.grad
    assert float(grad[:, 32:].abs().max()) > 0  # the variance half gets a gradient: it can learn to use it
