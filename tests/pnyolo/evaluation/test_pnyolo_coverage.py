"""Sampling coverage on hand-made geometry, and the items' 3D boxes the per-sample targets need."""
from __future__ import annotations

import numpy as np
import torch
from test_pnyolo_common import make_dataset, small_config

from dataset_spec.camera import project_points
from dataset_spec.synthetic import look_at, simple_intrinsics
from pnyolo.data.dataset import Draw, MultiViewDataset
from pnyolo.evaluation.coverage import CoverageAccumulator, object_coverage
from pnyolo.models import build_model, predict_item

PED = np.array([10.0, 0.0, 0.9, 0.6, 0.7, 1.8, 0.0])  # a pedestrian 10 m ahead of the first camera


def _side_view(width=64, height=48):
    """A second camera 8 m to the side, looking at the pedestrian; its visible pixels there."""
    K, c2w = simple_intrinsics(width, height), look_at((10.0, -8.0, 1.5), (10.0, 0.0, 1.0))
    corners = np.array([[PED[0] + sx * PED[3] / 2, PED[1] + sy * PED[4] / 2, PED[2] + sz * PED[5] / 2]
                        for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    uv, _ = project_points(K, c2w, corners)
    mask = np.zeros((height, width), bool)
    x0, y0 = np.floor(uv.min(0)).astype(int)
    x1, y1 = np.ceil(uv.max(0)).astype(int)
    mask[y0:y1 + 1, x0:x1 + 1] = True
    return K, c2w, mask


def _ray(z: float, t: np.ndarray) -> np.ndarray:
    """Points at distances t along a ray from (0, 0, z) along +x."""
    return np.stack([t, np.zeros_like(t), np.full_like(t, z)], axis=1)


def test_coverage_of_rays_that_miss_cross_between_samples_and_land_on_an_occluder():
    side = _side_view()
    # a ray that misses the box entirely (passing 1.2 m above it)
    miss = object_coverage(_ray(3.0, np.arange(2.0, 30.0, 0.25)), PED, [side], stride=2)
    assert not miss["in_box"] and not miss["on_pixels"]
    # a ray through the box, sampled 2.5 m apart with no sample inside its 0.6 m: it crosses between two
    between = object_coverage(_ray(0.9, np.array([8.5, 11.0, 13.5])), PED, [side], stride=2)
    assert not between["in_box"] and not between["on_pixels"]
    # one sample inside: in the box, and projected onto the other view's pixels of it
    hit = object_coverage(_ray(0.9, np.array([8.5, 10.1, 13.5])), PED, [side], stride=2)
    assert hit["in_box"] and hit["on_pixels"] and hit["near_pixels"]
    # a sample on an occluder 4 m in front: not in the box, and the other view sees it off the
    # pedestrian, though near enough to count within a generous stride
    occluder = object_coverage(_ray(0.9, np.array([6.0])), PED, [side], stride=2)
    assert not occluder["in_box"] and not occluder["on_pixels"] and not occluder["near_pixels"]
    assert object_coverage(_ray(0.9, np.array([6.0])), PED, [side], stride=40)["near_pixels"]
    # no view that sees it: nothing to land on
    assert not object_coverage(_ray(0.9, np.array([10.1])), PED, [], stride=2)["on_pixels"]


def test_items_carry_3d_boxes_that_project_into_their_labels_mirrored_or_not(tmp_path):
    root = make_dataset(tmp_path / "ds", n_scenarios=1)
    ds = MultiViewDataset(root, None, small_config(), training=False, scenarios=["toy_01"])
    model = build_model(ds.cfg, len(ds.class_names))
    for mirror in (False, True):
        item = ds.load("toy_01", ds.items[0].variant, [0, 1, 2], draw=Draw(mirror=mirror))
        targets = model.targets(item)
        boxes = item.boxes_3d.numpy().astype(np.float64)
        n = 0
        for v, gt in enumerate(item.gt):
            for box2d, row in zip(gt.boxes, gt.object_rows):
                uv, z = project_points(item.K[v].numpy(), item.camera_to_world[v].numpy(), boxes[row, :3])
                if z > 0.5:
                    x0, y0, x1, y1 = box2d
                    assert x0 - 1 <= uv[0] <= x1 + 1 and y0 - 1 <= uv[1] <= y1 + 1, (mirror, v, row)
                    n += 1
            target = targets[v]
            assert sorted(target[..., 8][target[..., 0] == 1].long().tolist()) == sorted((gt.object_rows + 1).tolist())
        assert n > 5


def test_coverage_counts_every_scored_object_and_thick_rays_meet_more_boxes(tmp_path):
    """At 64x48 with 8-pixel cells a road user is a few pixels tall: the one ray through its cell's
    centre often passes beside it; 3 x 3 rays per cell meet more of them."""
    root = make_dataset(tmp_path / "ds", n_scenarios=2)
    shares = {}
    for k in (1, 3):
        cfg = small_config(**{"model.sampler.cell_rays": k, "model.sampler.num_samples": 48})
        ds = MultiViewDataset(root, None, cfg, training=False, scenarios=["toy_01", "toy_02"])
        model = build_model(cfg, 2).eval()
        acc = CoverageAccumulator(ds.class_names, stride=min(model.encoder.strides))
        n_gt = 0
        for index in range(len(ds)):
            item = ds[index]
            with torch.no_grad():
                out = predict_item(model, item, "cpu", return_samples=True)
                acc.add_points(item, model.coverage_points(out, item), ds.instance_maps(item))
            n_gt += sum(len(g.boxes) for g in item.gt)
        summary = acc.summary()
        assert sum(r["n"] for groups in summary.values() for r in groups.values()) == n_gt
        hit = sum(r["in_box"] * r["n"] for groups in summary.values() for r in groups.values() if r["n"])
        shares[k] = hit / n_gt
    assert shares[3] > shares[1] + 0.1 and shares[3] > 0.5, shares
