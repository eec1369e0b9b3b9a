"""Ignored labels in items, ray-box intervals, per-sample occupancy targets, depth peaks and thick rays."""
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
from pnyolo.components.frustums import Frustums
from pnyolo.components.renderer import YoloRayRenderer
from pnyolo.data.targets import TARGET_CHANNELS, build_targets, decode_boxes, perfect_raw
from pnyolo.evaluation.metrics import (MetricAccumulator, ViewDetections, ViewGroundTruth, average_precision,
                                       ignored_predictions)
from pnyolo.decoding.nms import nms

torch.set_num_threads(2)
ANCHORS = torch.tensor([[0.02, 0.03], [0.04, 0.07], [0.08, 0.06]])



def test_items_mark_the_labels_the_thresholds_leave_out_as_ignored(tmp_path):
    from test_pnyolo_common import make_dataset, small_config

    from dataset_spec import LabelThresholds
    from pnyolo.data.dataset import MultiViewDataset
    from pnyolo.data.targets import IGNORE, OBJ
    from pnyolo.models import build_model
    from tools.projection import label_dataset

    root = make_dataset(tmp_path / "ds", n_scenarios=1, labels=False)
    label_dataset(root, thresholds=LabelThresholds(max_distance=12.0), progress=False)  # the far ones are left out
    ds = MultiViewDataset(root, None, small_config(), training=False, scenarios=["toy_01"])
    item = ds[0]
    targets = build_model(ds.cfg, len(ds.class_names)).targets(item)
    n_left_out = 0
    for v, gt in enumerate(item.gt):
        g = item.grid
        target = targets[v]
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
    samples = SampleOutputs(Frustums(origins, dirs, t, half), torch.ones(R, S, dtype=torch.bool), torch.zeros(R, S, A, 7),
                            cell)
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
    assert a.samples.frustums.t.shape == (cells, 16) and b.samples.frustums.t.shape == (4 * cells, 16 + 4)
    assert torch.equal(b.samples.cell, torch.arange(cells).repeat_interleave(4))
    # the fine samples lie inside each ray's interval, the coarse ones stand for bins, the fine for points
    t, half = b.samples.frustums.t, b.samples.frustums.half
    assert (half[:, :16] > 0).all() and (half[:, 16:] == 0).all()
    assert (t[:, 16:] >= t[:, :16].min(1, keepdim=True).values - half[:, :1]).all()
    # the four rays of a cell go through its sub-cells: they start at one camera, in four directions
    d = b.samples.frustums.dirs.reshape(cells, 4, 3)
    assert (torch.cdist(d, d) + torch.eye(4) > 1e-3).all()


def test_frustums_are_one_value_joined_along_samples_and_rays():
    """Issue 86, item 6: a sample's segment is one frozen value (nerfstudio's Frustums), not four parallel tensors."""
    o, d = torch.zeros(2, 3), torch.tensor([[1.0, 0, 0], [0, 1.0, 0]])
    coarse = Frustums(o, d, torch.tensor([[1.0, 3.0], [2.0, 4.0]]), torch.full((2, 2), 1.0), torch.full((2, 2), 0.5))
    fine = Frustums(o, d, torch.tensor([[2.5], [3.5]]), torch.zeros(2, 1), torch.zeros(2, 1))
    both = coarse.then(fine)
    assert both.t.tolist() == [[1.0, 3.0, 2.5], [2.0, 4.0, 3.5]] and both.half[:, 2].eq(0).all()
    torch.testing.assert_close(both.points()[1, 2], torch.tensor([0.0, 3.5, 0.0]))
    torch.testing.assert_close(coarse.radius(), torch.full((2, 2), (1.0 + 2 * 0.25) ** 0.5))  # half-diagonal too
    rays = Frustums.cat([coarse, coarse])
    assert rays.t.shape == (4, 2) and rays.origins.shape == (4, 3) and rays.lateral.shape == (4, 2)
    with pytest.raises(Exception):
        coarse.t = coarse.half  # frozen: a value, never written into
    assert Frustums(o, d, coarse.t, coarse.half).then(Frustums(o, d, fine.t, fine.half)).lateral is None
