"""The encoder, IoU / NMS, the metrics and config overrides on small hand-made inputs."""
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
from pnyolo.data.targets import TARGET_CHANNELS, build_targets, decode_boxes, perfect_raw
from pnyolo.evaluation.metrics import (MetricAccumulator, ViewDetections, ViewGroundTruth, average_precision,
                                       ignored_predictions)
from pnyolo.decoding.nms import nms

torch.set_num_threads(2)
ANCHORS = torch.tensor([[0.02, 0.03], [0.04, 0.07], [0.08, 0.06]])



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
                "model.encoder.eval_stats=batch", "model.loss.hidden_weight=-1", "model.loss.iou=-1",
                "model.encoder.context_channels=-8", "model.encoder.context_dilation=0"):
        with pytest.raises(UserError):
            load_config(None, [bad])


def test_decoding_every_view_in_one_pass_equals_decoding_each_view_alone():
    """Issue 64, item 3: decoding runs on the outputs' device for all views at once (one NMS with views kept apart,
    one copy to the host), with the detections view by view decoding gave."""
    from pnyolo.components.renderer import RayOutputs
    from pnyolo.data.grid import grid_for
    from pnyolo.decoding.yolo import decode_outputs

    torch.manual_seed(3)
    V, S_h, S_w, A, C, K = 3, 6, 8, 3, 2, 2
    out = RayOutputs(torch.rand(V, S_h, S_w, A), torch.randn(V, S_h, S_w, A, 4), torch.randn(V, S_h, S_w, A, C),
                     torch.rand(V, S_h, S_w, A) * 30)
    out.peaks = RayOutputs(torch.rand(V, S_h, S_w, A, K), torch.randn(V, S_h, S_w, A, K, 4),
                           torch.randn(V, S_h, S_w, A, K, C), torch.rand(V, S_h, S_w, A, K) * 30)
    anchors, grid = torch.tensor([[0.1, 0.2], [0.2, 0.3], [0.3, 0.2]]), grid_for(64, 48, 1.0, 8)
    for gap in (None, 3.0):
        together = decode_outputs(out, anchors, grid, 0.3, 0.4, gap)
        assert sum(len(d.scores) for d in together) > 10
        for v in range(V):
            fields = ("ray_confidence", "box", "class_logits", "depth")
            view = RayOutputs(*(getattr(out, f)[v:v + 1] for f in fields))
            view.peaks = RayOutputs(*(getattr(out.peaks, f)[v:v + 1] for f in fields))
            alone = decode_outputs(view, anchors, grid, 0.3, 0.4, gap)[0]
            for f in ("boxes", "scores", "classes", "distances"):
                np.testing.assert_array_equal(getattr(together[v], f), getattr(alone, f))


def test_greedy_suppression_is_the_same_box_by_box_and_in_rounds():
    """The CPU walks the boxes one by one; a GPU iterates the rule on all boxes at once: the same boxes kept."""
    from pnyolo.decoding.nms import greedy_keep

    rng = np.random.default_rng(0)
    for n in (0, 1, 7, 60):
        overlapping = torch.from_numpy(rng.random((n, n)) < 0.15).triu(1)
        assert torch.equal(greedy_keep(overlapping, rounds=False), greedy_keep(overlapping, rounds=True))


def test_nms_within_groups_one_group_at_a_time_equals_all_groups_at_once():
    """The CPU suppresses within each view's group separately (small matrices); a GPU masks one matrix of all
    the views' boxes: the same boxes kept, in the same order (highest score first, ties by position)."""
    from pnyolo.decoding.nms import _overlaps, greedy_keep, nms

    rng = np.random.default_rng(1)
    xy = torch.from_numpy(rng.random((300, 2)) * 100)
    boxes = torch.cat([xy, xy + torch.from_numpy(rng.random((300, 2)) * 20 + 5)], dim=1)
    scores = torch.from_numpy(rng.integers(0, 40, 300) / 40.0)  # ties on purpose
    groups, depths = torch.from_numpy(rng.integers(0, 3, 300)), torch.from_numpy(rng.random(300) * 30)
    for gap in (None, 4.0):
        order = torch.argsort(scores, descending=True, stable=True)
        together = _overlaps(boxes, order, 0.3, depths, gap) & (groups[order][:, None] == groups[order][None, :])
        expected = order[greedy_keep(together, rounds=True)]
        assert torch.equal(nms(boxes, scores, 0.3, depths, gap, groups=groups), expected)
