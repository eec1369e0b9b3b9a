"""Targets, loss, renderer, encoder, IoU/NMS and metrics on small hand-made inputs."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings, strategies as st

from dataset_spec.boxes import box_iou as np_box_iou, box_to_yolo, yolo_to_box as np_yolo_to_box
from pnyolo.components.boxes import box_iou, elementwise_iou_cxcywh, generalized_iou_cxcywh, yolo_to_box
from pnyolo.components.encoder import ResNetEncoder, index_features
from pnyolo.components.losses import YoloLoss
from pnyolo.components.mlp import COMBINE_FUNCTIONS, YoloMLP
from pnyolo.components.renderer import YoloRayRenderer
from pnyolo.config import LossConfig, MLPConfig
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
    loss = YoloLoss(LossConfig(box=0, obj=0, cls=0))
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
    """loss.iou: 1 - GIoU of each object anchor's decoded box; absent by default. The same shift
    in cell units costs a narrow box more than a wide one (the coordinate MSE costs both alike),
    and a box that misses its object entirely still gets a gradient towards it."""
    def setup(w):
        target = build_targets(torch.tensor([[0.5 / 8 + 0.01, 0.5 / 6, w, 0.1]]), torch.tensor([0]), 6, 8,
                               torch.tensor([[w, 0.1]]))
        return target, perfect_raw(target, torch.tensor([[w, 0.1]]), 2)
    fn = YoloLoss(LossConfig(iou=1.0))
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
    only_iou = YoloLoss(LossConfig(box=0, obj=0, noobj=0, cls=0, iou=1.0))
    only_iou(raw["ray_confidence"], box, raw["class_logits"], target, torch.tensor([[0.02, 0.1]]))[0].backward()
    obj = target[..., 0] == 1
    assert float(box.grad[obj][0, 0]) < 0  # descending moves the box right, towards its object
    assert "iou" not in YoloLoss()(raw["ray_confidence"], raw["box"], raw["class_logits"], target,
                                   torch.tensor([[0.02, 0.1]]))[1]


def test_distance_term_is_zero_when_right_absent_without_distances_and_moves_confidence_to_the_object():
    """loss.depth: Huber of the rendered distance against the target's, only where both exist; its
    gradient concentrates an anchor's confidence on the samples at its object's distance."""
    boxes, classes, W, H = _gt()
    yolo = torch.tensor(np.stack([box_to_yolo(b, W, H) for b in boxes]), dtype=torch.float32)
    dist = torch.tensor([6.0, 9.0, 12.0, 15.0])
    target = build_targets(yolo, torch.tensor(classes), 18, 32, ANCHORS, 0.5, distances=dist)
    obj = target[..., 0] == 1
    assert sorted(target[obj][:, 7].tolist()) == dist.tolist()
    raw = perfect_raw(target, ANCHORS, 2)
    fn = YoloLoss(LossConfig(depth=1.0))
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
    only_depth = YoloLoss(LossConfig(box=0, obj=0, noobj=0, cls=0, depth=1.0))
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
        fn = YoloLoss(LossConfig(box=0, obj=1, noobj=0, cls=0, obj_target="one", obj_loss=kind))
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
    ones = build_targets(yolo, torch.tensor(classes), 18, 32, ANCHORS, 0.5, weights=torch.ones(4))
    torch.testing.assert_close(plain, ones)
    raw = perfect_raw(plain, ANCHORS, 2)
    fn = YoloLoss()

    def added_by_missing(k: int, weight: float) -> dict[str, float]:
        """Each term's increase when object k is predicted wrong (low confidence, shifted box, wrong class)."""
        w = torch.ones(4)
        w[k] = weight
        target = build_targets(yolo, torch.tensor(classes), 18, 32, ANCHORS, 0.5, weights=w)
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
    from pnyolo.data.dataset import object_loss_weights

    vis = [0.0, 0.0, 0.3, 1.0, 0.0]
    seen = [True, False, False, True, True]
    w = object_loss_weights(vis, seen, LossConfig(hidden_weight=3.0, unseen_weight=0.0))
    assert w.tolist() == [3.0, 0.0, 1.0, 1.0, 3.0]
    assert object_loss_weights(vis, seen, LossConfig()).tolist() == [1.0] * 5  # the paper: all alike
    assert object_loss_weights([], [], LossConfig(hidden_weight=2.0)).shape == (0,)


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
    loss, terms = YoloLoss(LossConfig(depth=1.0))(out.ray_confidence.reshape(2, 3, 3), out.box.reshape(2, 3, 3, 4),
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


def test_encoder_has_torchvision_names_and_loads_a_local_state_dict(tmp_path):
    enc = ResNetEncoder("resnet34", num_layers=5)
    keys = set(enc.state_dict())
    for k in ("conv1.weight", "bn1.running_mean", "layer1.2.conv2.weight", "layer2.0.downsample.0.weight",
              "layer2.0.downsample.1.bias", "layer3.5.bn2.weight", "layer4.2.conv1.weight"):
        assert k in keys
    n_params = sum(p.numel() for n, p in enc.named_parameters())
    assert n_params == 21284672  # torchvision resnet34 without fc (21797672 - 513000)
    state = {k: torch.randn_like(v) if v.dtype.is_floating_point else v for k, v in enc.state_dict().items()}
    state["fc.weight"], state["fc.bias"] = torch.zeros(1000, 512), torch.zeros(1000)
    torch.save(state, tmp_path / "w.pth")
    small = ResNetEncoder("resnet34", num_layers=4)
    ignored = small.load_weights(tmp_path / "w.pth")
    assert "fc.weight" in ignored and torch.equal(small.layer3[0].conv1.weight, state["layer3.0.conv1.weight"])
    feats = small(torch.rand(2, 3, 64, 96))
    assert [f.shape[1] for f in feats] == [64, 64, 128, 256] and small.latent_size == 512
    idx = index_features(feats, torch.zeros(2, 7, 2), small.strides)
    assert idx.shape == (2, 7, 512)


@pytest.mark.parametrize("backbone,num_layers,context", [("resnet18", 2, 16), ("resnet34", 5, 0)])
def test_features_are_read_at_the_requested_pixel_at_every_stride(backbone, num_layers, context):
    """Maps shaped as the real encoder makes them for a 180x320 image, each feature holding the image
    pixel it is centred on (stride * index): indexing any pixel returns that pixel (bilinear
    interpolation of a linear map is exact), within 0.05 px on every map."""
    enc = ResNetEncoder(backbone, num_layers=num_layers, context_channels=context)
    shapes = [f.shape[-2:] for f in enc(torch.rand(1, 3, 180, 320))]
    maps = []
    for (h, w), s in zip(shapes, enc.strides):
        v, u = torch.meshgrid(torch.arange(h) * float(s), torch.arange(w) * float(s), indexing="ij")
        maps.append(torch.stack([u, v])[None])  # (1, 2, h, w): channel 0 = u, 1 = v
    last = min(s * (w - 1) for (h, w), s in zip(shapes, enc.strides)), min(s * (h - 1) for (h, w), s in zip(shapes, enc.strides))
    uv = torch.stack([torch.rand(500) * last[0], torch.rand(500) * last[1]], dim=-1)[None]  # inside every map
    read = index_features(maps, uv, enc.strides).reshape(1, 500, len(maps), 2)
    assert (read - uv[:, :, None]).abs().max() < 0.05


def test_encoder_context_features_are_a_learned_map_of_the_neighbours(tmp_path):
    """context_channels: one more feature map, a dilated 3x3 convolution of the last one, indexed
    like the others; it responds to a change a dilation away from the point where the plain
    features at that point do not. Pretrained weights (no context keys) still load, and freezing
    the ResNet leaves the context convolution trainable."""
    torch.manual_seed(0)
    enc = ResNetEncoder("resnet18", num_layers=2, context_channels=16, context_dilation=2).eval()
    plain = ResNetEncoder("resnet18", num_layers=2)
    assert enc.latent_size == plain.latent_size + 16
    x = torch.rand(1, 3, 64, 96)
    with torch.no_grad():
        feats = enc(x)
    assert [f.shape[1] for f in feats] == [64, 64, 16] and feats[2].shape[2:] == feats[1].shape[2:]
    # A layer1 feature (stride 4) changed 2 cells to the right (8 px): the point's own layer1
    # feature is unchanged, its context feature is not.
    f1 = feats[1].clone()
    f1[..., 8, 12 + 2] += 1.0
    with torch.no_grad():
        ctx = enc.context(f1)
    assert torch.equal(f1[..., 8, 12], feats[1][..., 8, 12])
    assert float((ctx[..., 8, 12] - feats[2][..., 8, 12]).abs().max()) > 1e-4
    torch.save(plain.state_dict(), tmp_path / "plain.pth")
    assert enc.load_weights(tmp_path / "plain.pth") == []
    frozen = ResNetEncoder("resnet18", num_layers=2, freeze=True, context_channels=8)
    assert all(p.requires_grad for p in frozen.context.parameters())
    assert not any(p.requires_grad for n, p in frozen.named_parameters() if not n.startswith("context."))


def test_encoder_freeze():
    enc = ResNetEncoder("resnet18", num_layers=3, freeze=True)
    assert not any(p.requires_grad for p in enc.parameters())
    enc.train()
    assert not enc.bn1.training


def test_encoder_item_statistics_outside_training_are_the_training_ones():
    """eval_stats=item: outside training, batch norm uses the statistics of the views encoded
    together (exactly what a training step computes) and leaves the running averages alone;
    running: PyTorch's default, which differs; frozen batch norm always uses the running ones."""
    torch.manual_seed(0)
    enc = ResNetEncoder("resnet18", num_layers=3)
    enc.train()
    with torch.no_grad():
        for _ in range(3):  # running averages from other batches
            enc(torch.rand(3, 3, 32, 48) * 0.5)
    x = torch.rand(3, 3, 32, 48)
    state = {k: v.clone() for k, v in enc.state_dict().items()}
    with torch.no_grad():
        trained = enc(x)
        enc.load_state_dict(state)
        enc.eval()
        running = enc(x)
        enc.set_eval_stats("item")
        item = enc(x)
    assert all(torch.equal(v, enc.state_dict()[k]) for k, v in state.items())  # nothing updated
    for t, r, i in zip(trained, running, item):
        torch.testing.assert_close(i, t)
        assert float((r - t).abs().max()) > 0.1
    frozen = ResNetEncoder("resnet18", num_layers=3, frozen_batchnorm=True, eval_stats="item")
    frozen.load_state_dict(state)
    with torch.no_grad():
        torch.testing.assert_close(frozen.eval()(x)[0], running[0])
    with pytest.raises(ValueError):
        enc.set_eval_stats("batch")


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 25), st.integers(0, 25), st.integers(0, 10_000))
@example(21, 2, 21)  # gated NMS keeps a box that then suppresses one plain NMS keeps
def test_iou_and_nms_match_brute_force(n, m, seed):
    rng = np.random.default_rng(seed)

    def boxes(k):
        xy = rng.uniform(0, 100, (k, 2))
        return np.concatenate([xy, xy + rng.uniform(1, 40, (k, 2))], 1)
    a, b = boxes(n), boxes(m)
    np.testing.assert_allclose(box_iou(torch.tensor(a), torch.tensor(b)).numpy(), np_box_iou(a, b), atol=1e-9)
    scores = rng.uniform(0, 1, n)
    keep = nms(torch.tensor(a), torch.tensor(scores), 0.5).tolist()
    ref = []
    for i in np.argsort(-scores, kind="stable"):
        if all(np_box_iou(a[i:i + 1], a[j:j + 1])[0, 0] <= 0.5 for j in ref):
            ref.append(int(i))
    assert keep == ref
    # depth-gated: a box is suppressed only by a kept one that overlaps it at a similar distance
    depths = rng.uniform(4, 26, n)
    depths[::3] = np.nan  # no distance: gated like plain NMS
    gated = nms(torch.tensor(a), torch.tensor(scores), 0.5, torch.tensor(depths), 3.0).tolist()
    ref = []
    for i in np.argsort(-scores, kind="stable"):
        if all(np_box_iou(a[i:i + 1], a[j:j + 1])[0, 0] <= 0.5 or abs(depths[i] - depths[j]) > 3.0 for j in ref):
            ref.append(int(i))
    assert gated == ref
    # a gap wider than every depth difference gates nothing: plain NMS (gating is not monotone: a box
    # it keeps may suppress one that plain NMS keeps, so the kept sets need not nest)
    assert nms(torch.tensor(a), torch.tensor(scores), 0.5, torch.tensor(depths), 100.0).tolist() == keep


def test_depth_gated_nms_keeps_a_road_user_behind_its_occluder():
    occluder, hidden = [10.0, 10.0, 50.0, 40.0], [14.0, 12.0, 48.0, 38.0]  # IoU 0.71
    boxes, scores = torch.tensor([occluder, hidden]), torch.tensor([0.9, 0.6])
    assert nms(boxes, scores, 0.5).tolist() == [0]
    assert nms(boxes, scores, 0.5, torch.tensor([8.0, 16.0]), 4.0).tolist() == [0, 1]
    assert nms(boxes, scores, 0.5, torch.tensor([8.0, 10.0]), 4.0).tolist() == [0]  # a duplicate
    assert nms(boxes, scores, 0.5, torch.tensor([8.0, float("nan")]), 4.0).tolist() == [0]
    assert nms(boxes, scores, 0.5, torch.tensor([8.0, 16.0]), None).tolist() == [0]


def _det(boxes, scores, classes):
    return ViewDetections(np.array(boxes, float).reshape(-1, 4), np.array(scores, float), np.array(classes))


def _gts(boxes, classes):
    return ViewGroundTruth(np.array(boxes, float).reshape(-1, 4), np.array(classes))


def test_metric_counts_on_hand_made_case_both_modes():
    gt = _gts([[0, 0, 10, 10], [20, 20, 30, 30], [50, 50, 60, 60]], [0, 0, 1])
    det = _det([[0, 0, 10, 10],     # exact hit of gt0
                [1, 1, 10, 10],     # duplicate on gt0 (IoU .81)
                [20, 20, 30, 30],   # hits gt1 but wrong class
                [100, 100, 110, 110]],  # nothing
               [0.9, 0.8, 0.7, 0.6], [0, 0, 1, 0])
    acc = MetricAccumulator([0.5], num_classes=2)
    acc.add(det, gt)
    s = acc.counts(0.5, "strict")
    assert (s["tp"], s["fp"], s["fn"]) == (1, 3, 2)
    assert s["precision"] == pytest.approx(0.25) and s["recall"] == pytest.approx(1 / 3)
    p = acc.counts(0.5, "paper")  # any-class best IoU, not one-to-one: 3 predictions count
    assert (p["tp"], p["fp"]) == (3, 1)
    assert p["precision"] == pytest.approx(0.75) and p["recall"] == pytest.approx(1.0)
    assert p["f1"] == pytest.approx(2 * 0.75 / 1.75)


def test_metric_recall_breakdown_and_empty_views():
    gt = ViewGroundTruth(np.array([[0, 0, 10, 10], [20, 20, 30, 30], [40, 40, 50, 50]], float), np.array([0, 0, 0]),
                         np.array([0.0, 0.5, 0.9]), np.array([True, False, True]))
    det = _det([[0, 0, 10, 10], [40, 40, 50, 50]], [0.9, 0.8], [0, 0])
    acc = MetricAccumulator([0.4], num_classes=1)
    acc.add(det, gt)
    acc.add(_det([], [], []), _gts([], []))
    rb = acc.recall_breakdown(0.4)
    assert rb["visible 0%"]["recall"] == 1.0 and rb["visible 40-80%"]["recall"] == 0.0
    assert rb["seen in another view"] == {"recall": 1.0, "n": 2}
    assert rb["not seen in another view"] == {"recall": 0.0, "n": 1}
    assert acc.summary()["strict"]["0.4"]["tp"] == 2


def test_false_positive_breakdown_on_hand_made_case():
    gt = ViewGroundTruth(np.array([[0, 0, 10, 10], [20, 20, 30, 30]], float), np.array([0, 0]),
                         excluded_boxes=np.array([[60, 60, 70, 70]], float))
    det = _det([[0, 0, 10, 10],        # TP
                [1, 1, 10, 10],        # duplicate on gt0
                [20, 20, 30, 30],      # on gt1 but the wrong class
                [60, 60, 70, 70],      # a road user left out of the ground truth (e.g. too far)
                [28, 28, 40, 40],      # grazes gt1
                [100, 100, 110, 110]],  # nothing there: a ghost
               [0.9, 0.8, 0.7, 0.6, 0.5, 0.4], [0, 0, 1, 0, 0, 0])
    acc = MetricAccumulator([0.5], num_classes=2)
    acc.add(det, gt)
    fp = acc.summary()["false_positives"]["0.5"]
    assert fp["n"] == acc.counts(0.5)["fp"] == 4  # the excluded road user's detection is ignored
    assert [fp[k]["count"] for k in ("on a ground-truth object", "near an object", "on no labelled object")] == [2, 1, 1]
    assert fp["ignored"] == 1
    assert sum(v["share"] for v in fp.values() if isinstance(v, dict)) == pytest.approx(1.0)
    empty = MetricAccumulator([0.5], num_classes=2)
    empty.add(_det([[0, 0, 5, 5]], [0.5], [0]), ViewGroundTruth(np.zeros((0, 4)), np.zeros(0, int)))
    assert empty.false_positive_breakdown(0.5)["on no labelled object"]["count"] == 1


def test_detections_of_excluded_road_users_are_neither_true_nor_false_positives():
    """COCOeval's crowd rule: an unmatched detection covering a road user outside the ground truth
    (too far, too truncated) of its class, intersection over its own area >= the threshold, is
    ignored, in counts, AP and the threshold sweep's per-view counts alike; one that covers the
    excluded one too little, or an excluded road user of another class, stays a FP."""
    gt = ViewGroundTruth(np.array([[0, 0, 10, 10]], float), np.array([0]),
                         excluded_boxes=np.array([[60, 60, 70, 70], [2, 2, 12, 12]], float))
    det = _det([[0, 0, 10, 10],      # TP
                [60, 60, 70, 70],    # the far road user: ignored
                [1, 1, 11, 11],      # duplicate of the GT, but 81 % of it covers the second excluded box: ignored
                [66, 66, 76, 76]],   # grazes the far road user (16 % of it): FP
               [0.9, 0.95, 0.7, 0.6], [0, 0, 0, 0])
    acc = MetricAccumulator([0.5], num_classes=1)
    acc.add(det, gt)
    assert {k: acc.counts(0.5)[k] for k in ("tp", "fp", "fn")} == {"tp": 1, "fp": 1, "fn": 0}
    assert acc.per_view_counts(0.5).tolist() == [[1, 1, 0]]
    other = ViewGroundTruth(gt.boxes, gt.classes, excluded_boxes=gt.excluded_boxes, excluded_classes=np.array([1, 1]))
    inside = _det([[62, 62, 68, 68]], [0.5], [0])  # wholly inside an excluded road user, of another class: FP
    assert ignored_predictions(inside, other, np.array([False]), 0.5).tolist() == [False]
    assert ignored_predictions(inside, gt, np.array([False]), 0.5).tolist() == [True]  # no classes: any class
    paper = acc.counts(0.5, "paper")  # the original counting: duplicates hit, nothing ignored
    assert (paper["tp"], paper["fp"]) == (2, 2)
    # AP: the ignored top-scoring detection does not push the TP down the ranking
    top = MetricAccumulator([0.5], num_classes=1)
    top.add(_det([[60, 60, 70, 70], [0, 0, 10, 10]], [0.95, 0.9], [0, 0]), gt)
    assert top.summary()["ap50"] == pytest.approx(1.0)
    without = ViewGroundTruth(gt.boxes, gt.classes)  # no excluded boxes: the same detection is a FP first
    assert average_precision([(_det([[60, 60, 70, 70], [0, 0, 10, 10]], [0.95, 0.9], [0, 0]), without)], 0.5, 1) \
        == pytest.approx(0.5, abs=0.01)


def test_average_precision_perfect_and_half():
    gt = _gts([[0, 0, 10, 10], [20, 20, 30, 30]], [0, 0])
    assert average_precision([(_det([[0, 0, 10, 10], [20, 20, 30, 30]], [0.9, 0.8], [0, 0]), gt)], 0.5, 1) == pytest.approx(1.0)
    ap = average_precision([(_det([[0, 0, 10, 10]], [0.9], [0]), gt)], 0.5, 1)
    assert ap == pytest.approx(51 / 101)


def test_config_overrides_parse_like_a_user_types_them():
    from dataset_spec.cli_support import UserError
    from pnyolo.config import load_config

    cfg = load_config(None, ["train.lr=1e-3", "train.epochs=3", "model.sampler.slab_clip=true",
                             "model.head.anchors=[[0.1,0.2],[0.3,0.4]]"])
    assert cfg.train.lr == 0.001 and cfg.train.epochs == 3 and cfg.model.sampler.slab_clip is True
    assert cfg.model.head.anchors == [[0.1, 0.2], [0.3, 0.4]]
    for bad in ("train.lr=fast", "train.epochs=2.5", "model.sampler.slab_clip=maybe", "train.nope=1",
                "model.encoder.eval_stats=batch", "loss.hidden_weight=-1", "loss.iou=-1",
                "model.encoder.context_channels=-8", "model.encoder.context_dilation=0"):
        with pytest.raises(UserError):
            load_config(None, [bad])


def test_items_mark_the_labels_the_thresholds_leave_out_as_ignored(tmp_path):
    from test_pnyolo_common import make_dataset, small_config

    from dataset_spec import LabelThresholds
    from pnyolo.data.dataset import MultiViewDataset
    from pnyolo.data.targets import IGNORE, OBJ
    from tools.projection import label_dataset

    root = make_dataset(tmp_path / "ds", n_scenarios=1, labels=False)
    label_dataset(root, thresholds=LabelThresholds(max_distance=12.0), progress=False)  # the far ones are left out
    ds = MultiViewDataset(root, None, small_config(), training=False, scenarios=["toy_01"])
    item = ds[0]
    n_left_out = 0
    for v, gt in enumerate(item.gt):
        g = item.grid
        target = item.targets[v]
        for box in gt.excluded_boxes:  # each left-out road user's centre cell is ignored (or holds an object)
            u, w = ((box[0] + box[2]) / 2 + 0.5) / g.width, ((box[1] + box[3]) / 2 + 0.5) / g.height  # image fractions
            row, col = min(int(w * g.grid_h), g.grid_h - 1), min(int(u * g.grid_w), g.grid_w - 1)
            assert ((target[row, col, :, 0] == IGNORE) | (target[row, col, :, 0] == OBJ)).all()
            n_left_out += 1
        assert (target[..., 0] == OBJ).sum() == len(gt.boxes)
    assert n_left_out > 0


def test_ray_box_intervals_match_points_along_the_rays_for_yawed_boxes():
    from dataset_spec.boxes import points_in_box
    from pnyolo.components.occupancy import ray_box_intervals

    g = torch.Generator().manual_seed(4)
    boxes = torch.tensor([[5.0, 1.0, 0.9, 0.6, 0.7, 1.8, 0.4], [12.0, -2.0, 1.0, 4.5, 1.9, 1.6, -1.1],
                          [-3.0, 0.0, 1.5, 12.0, 2.5, 3.0, 2.0]])
    origins = torch.tensor([0.0, 0.0, 1.4]).expand(200, 3)
    dirs = torch.nn.functional.normalize(torch.randn(200, 3, generator=g) * torch.tensor([1.0, 0.4, 0.1]), dim=-1)
    t_in, t_out = ray_box_intervals(origins, dirs, boxes)
    t = torch.linspace(0, 30, 3001)
    points = origins[:, None] + t[None, :, None] * dirs[:, None]  # (R, T, 3)
    for n, b in enumerate(boxes.numpy()):
        inside = points_in_box(points.reshape(-1, 3).numpy(), b[:3], b[3:6], float(b[6])).reshape(200, -1)
        hit = torch.from_numpy(inside)
        want = (t_in[:, n, None] <= t[None]) & (t[None] <= t_out[:, n, None]) & (t_in[:, n] <= t_out[:, n])[:, None]
        assert (want != hit).sum() <= 2 * 200 * 1  # at most the boundary sample of each crossing
        assert hit.any(dim=1).sum() > 3  # some rays cross each box


def test_occupancy_targets_match_a_brute_force_loop_over_boxes_and_samples():
    from dataset_spec.boxes import points_in_box
    from pnyolo.components.occupancy import sample_targets
    from pnyolo.components.renderer import SampleOutputs
    from pnyolo.data.targets import IGNORE, OBJ, OBJECT

    g = torch.Generator().manual_seed(7)
    boxes = torch.tensor([[8.0, 0.3, 0.9, 0.6, 0.7, 1.8, 0.3], [9.5, 0.0, 0.8, 4.5, 1.9, 1.6, 0.2],
                          [20.0, 3.0, 0.8, 4.0, 1.8, 1.5, 1.0]])
    R, S, A = 40, 24, 2
    origins = torch.tensor([0.0, 0.0, 1.0]).expand(R, 3)
    dirs = torch.nn.functional.normalize(torch.tensor([1.0, 0.0, -0.01]) + 0.03 * torch.randn(R, 3, generator=g), dim=-1)
    t = torch.sort(torch.rand(R, S, generator=g) * 25 + 1, dim=1).values
    half = torch.where(torch.arange(S) < 16, 0.6, 0.0).expand(R, S)  # 16 coarse (bins of 1.2 m), 8 fine
    targets = torch.zeros(1, 2, 5, A, 9)
    targets[0, 0, 1, 0, 0], targets[0, 0, 1, 0, OBJECT] = OBJ, 1  # cell 1: the pedestrian (box 0) on anchor 0
    targets[0, 0, 1, 1, 0], targets[0, 0, 1, 1, OBJECT] = OBJ, 2  # ... and the car behind it on anchor 1
    targets[0, 0, 2, 1, 0] = IGNORE
    cell = torch.randint(0, 10, (R,), generator=g)
    cell[:10] = 1
    samples = SampleOutputs(origins, dirs, t, half, torch.ones(R, S, dtype=torch.bool), torch.zeros(R, S, A, 7), cell)
    positive, counted, _ = sample_targets(samples, targets, boxes)
    for r in range(R):
        tgt = targets.reshape(-1, A, 9)[cell[r]]
        for s in range(S):
            ts = torch.linspace(t[r, s] - half[r, s], t[r, s] + half[r, s], 61) if half[r, s] > 0 else t[r, s:s + 1]
            pts = (origins[r] + ts[:, None] * dirs[r]).numpy()
            hits = [bool(points_in_box(pts, b[:3], b[3:6], float(b[6])).any()) for b in boxes.numpy()]
            for a in range(A):
                own = int(tgt[a, OBJECT]) - 1 if tgt[a, 0] == OBJ else -1
                pos = own >= 0 and hits[own]
                other = any(h for n, h in enumerate(hits) if n != own)
                assert bool(positive[r, s, a]) == pos, (r, s, a)
                assert bool(counted[r, s, a]) == (tgt[a, 0] != IGNORE and (pos or not other)), (r, s, a)
    assert positive[:, :, 0].any() and positive[:, :, 1].any()  # both the pedestrian and the car it hides


def test_depth_peaks_keep_an_occluder_and_the_road_user_behind_it_apart():
    """One ray crossing two boxes (confidence bumps at 8 m and 15 m, each sample's box its own)
    yields two candidates at those depths with their own boxes; one box yields one candidate
    above background; peaks=1 is the paper's aggregate."""
    t = torch.linspace(2, 30, 57)[None]  # 0.5 m apart
    raw = torch.full((1, 57, 1, 7), -5.0)
    raw[..., 1:] = 0.0
    front, back = (t[0] - 8).abs() <= 1.0, (t[0] - 15).abs() <= 0.5
    raw[0, front, 0, 0], raw[0, back, 0, 0] = 3.0, 2.0
    raw[0, front, 0, 3], raw[0, back, 0, 3] = 1.0, -1.0  # tw: the occluder wide, the hidden one narrow
    valid = torch.ones(1, 57, dtype=torch.bool)
    two = YoloRayRenderer()(raw, t, valid, peaks=2, gap=2.0).peaks
    assert two.ray_confidence.shape == (1, 1, 2)
    assert two.ray_confidence[0, 0].tolist() == pytest.approx([torch.sigmoid(torch.tensor(3.0)).item(),
                                                               torch.sigmoid(torch.tensor(2.0)).item()], abs=1e-5)
    assert two.depth[0, 0].tolist() == pytest.approx([8.0, 15.0], abs=0.1)
    assert two.box[0, 0, :, 2].tolist() == pytest.approx([1.0, -1.0], abs=0.05)
    raw_one = raw.clone()
    raw_one[0, back, 0, 0] = -5.0
    one = YoloRayRenderer()(raw_one, t, valid, peaks=2, gap=2.0).peaks
    assert one.ray_confidence[0, 0, 0] > 0.9 and one.ray_confidence[0, 0, 1] < 0.01  # nothing else above background
    paper = YoloRayRenderer()(raw, t, valid)
    assert paper.peaks is None and paper.ray_confidence[0, 0] == two.ray_confidence[0, 0, 0]
    assert 8.0 < float(paper.depth[0, 0]) < 15.0  # the blend the peaks avoid


def test_thick_rays_and_hierarchical_samples_render_one_output_per_cell():
    from test_pnyolo_common import small_config

    from pnyolo.data.grid import grid_for
    from pnyolo.models import build_model

    torch.manual_seed(0)
    grid = grid_for(64, 48, 1.0, 8)
    K = torch.tensor([[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]]).expand(3, 3, 3)
    c2w = torch.eye(4).expand(3, 4, 4).clone()
    c2w[:, :3, :3] = torch.tensor([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # looking along +y, z up
    c2w[:, :3, 3] = torch.tensor([[0, 0, 1.5], [1, 0, 1.5], [-1, 0, 1.5]])
    images = torch.rand(3, 3, 48, 64)
    plain = build_model(small_config(), 2).eval()
    thick = build_model(small_config(**{"model.sampler.cell_rays": 2, "model.sampler.fine_samples": 4}), 2).eval()
    with torch.no_grad():
        a = plain(images, K, c2w, grid, return_samples=True)
        b = thick(images, K, c2w, grid, return_samples=True)
    cells = 3 * grid.grid_h * grid.grid_w
    assert a.ray_confidence.shape == b.ray_confidence.shape == (3, grid.grid_h, grid.grid_w, 3)
    assert a.samples.t.shape == (cells, 16) and b.samples.t.shape == (4 * cells, 16 + 4)
    assert torch.equal(b.samples.cell, torch.arange(cells).repeat_interleave(4))
    # the fine samples lie inside each ray's interval, the coarse ones stand for bins, the fine for points
    t, half = b.samples.t, b.samples.half_width
    assert (half[:, :16] > 0).all() and (half[:, 16:] == 0).all()
    assert (t[:, 16:] >= t[:, :16].min(1, keepdim=True).values - half[:, :1]).all()
    # the four rays of a cell go through its sub-cells: they start at one camera, in four directions
    d = b.samples.dirs.reshape(cells, 4, 3)
    assert (torch.cdist(d, d) + torch.eye(4) > 1e-3).all()
