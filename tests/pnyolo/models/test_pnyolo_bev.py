"""The ground-plane model's pieces: grid, pillar sampling, targets, decoding into views, late fusion,
and the 3D metrics on hand-computed cases."""
from __future__ import annotations

import itertools
import math

import cv2
import numpy as np
import pytest
import torch
from test_pnyolo_common import make_dataset, tiny

from dataset_spec.cli_support import UserError
from pnyolo.components.bev_grid import BevGrid, grid_for_cameras, pillar_points, project_pillars
from pnyolo.components.encoder import index_features
from pnyolo.components.geometry import Cameras
from pnyolo.config import load_config
from pnyolo.components.bev_targets import bev_targets, decode_regression, positive_rows
from pnyolo.data.dataset import Draw, MultiViewDataset
from pnyolo.cooperation.late_fusion import pool_cars
from pnyolo.evaluation.metrics import ViewDetections, ViewGroundTruth
from pnyolo.evaluation.metrics_3d import hungarian, metrics_3d
from pnyolo.decoding.world import WorldDetections, centre_nms, project_into_views

BEV = tiny("model.kind=bev")


@pytest.fixture(scope="module")
def item(tmp_path_factory):
    root = make_dataset(tmp_path_factory.mktemp("bev") / "ds", n_scenarios=1, width=160, height=120)
    cfg = load_config(None, BEV)
    return MultiViewDataset(root, "train", cfg, views=[0, 1, 2])[0]


def _grid(item, **kw) -> BevGrid:
    g = item.grid
    return grid_for_cameras(Cameras(item.K, item.camera_to_world, g.width, g.height), item.scored, **kw)


def test_the_grid_covers_every_scored_camera_and_refuses_bad_bounds(item):
    g = _grid(item, cell=0.4, range_m=40.0)
    assert g.nx % 4 == 0 and g.ny % 4 == 0
    for c2w in item.camera_to_world:
        iy, ix = g.cell_of(c2w[:2, 3])
        assert g.inside(iy, ix)
    boxes = item.boxes_3d
    assert bool(g.inside(*g.cell_of(boxes[:, :2])).all()), "every road user of the toy scene lies on the grid"
    with pytest.raises(UserError, match="cover no camera"):
        _grid(item, cell=0.4, range_m=40.0, bounds=[500, 500, 520, 520])
    with pytest.raises(UserError, match="max_cells"):
        _grid(item, cell=0.4, range_m=40.0, max_cells=100)


def test_a_fixed_grid_is_mirrored_with_a_mirrored_item(tmp_path):
    """data.hflip with model.bev.bounds: a mirrored item sees the world mirrored in x = 0, so its grid is
    the bounds mirrored too; training with both runs (it stopped at the first mirrored step before)."""
    from pnyolo.cli import train_main
    from pnyolo.models import build_model

    root = make_dataset(tmp_path / "ds", n_scenarios=1)
    sets = tiny("model.kind=bev", "model.bev.bounds=[1,-20,28,20]", "data.hflip=true")  # not symmetric in x
    cfg = load_config(None, sets)
    model = build_model(cfg, 2)
    ds = MultiViewDataset(root, "train", cfg, views=[0, 1, 2])
    plain, mirrored = ds.load(ds.scenarios[0], ds.items[0].variant, [0, 1, 2], draw=Draw(mirror=False)), \
        ds.load(ds.scenarios[0], ds.items[0].variant, [0, 1, 2], draw=Draw(mirror=True))
    g = model.grid_for(plain.K, plain.camera_to_world, plain.grid.width, plain.grid.height, [0, 1, 2])
    gm = model.grid_for(mirrored.K, mirrored.camera_to_world, mirrored.grid.width, mirrored.grid.height, [0, 1, 2],
                        mirrored=True)
    assert (g.nx, g.ny) == (gm.nx, gm.ny)
    assert g.x0 <= 1.0 and float(gm.x0) == pytest.approx(-(g.x0 + g.nx * g.cell))
    inside = lambda grid, boxes: grid.inside(*grid.cell_of(boxes[:, :2])).tolist()  # noqa: E731
    assert inside(g, plain.boxes_3d) == inside(gm, mirrored.boxes_3d)  # the same road users on the grid
    argv = [str(root), "--out", str(tmp_path / "run"), "--quiet",
            *sum((["--set", s] for s in sets + ["train.max_steps=6", "train.epochs=6", "train.seed=1"]), [])]
    assert train_main(argv) == 0


def test_pillar_sampling_reads_the_pixel_cv2_projects_to(item):
    """A feature map holding its own pixel coordinates, indexed at a pillar point's projection,
    returns cv2.projectPoints of that point."""
    g = BevGrid(-6.0, -6.0, 0.4, 32, 32)
    points = pillar_points(g, [0.25, 1.25, 2.25], 0.0)
    uv, ok = project_pillars(item.K, item.camera_to_world, points, item.grid.width, item.grid.height)
    H, W = item.grid.height, item.grid.width
    for stride in (2, 4):
        fu = torch.arange(0, W, stride, dtype=torch.float32)  # feature j is centred on pixel stride * j
        fv = torch.arange(0, H, stride, dtype=torch.float32)
        fmap = torch.stack([fu[None, :].expand(len(fv), -1), fv[:, None].expand(-1, len(fu))])[None].expand(3, -1, -1, -1)
        V = uv.shape[0]
        read = index_features([fmap], uv.reshape(V, -1, 2), [stride]).reshape(*uv.shape)
        for v in range(V):
            c2w = item.camera_to_world[v].numpy().astype(np.float64)
            w2c = np.linalg.inv(c2w)
            rvec, _ = cv2.Rodrigues(w2c[:3, :3])
            ref, _ = cv2.projectPoints(points.reshape(-1, 3).numpy().astype(np.float64), rvec, w2c[:3, 3],
                                       item.K[v].numpy().astype(np.float64), None)
            ref = ref.reshape(*uv.shape[1:])
            inner = ok[v] & (uv[v, ..., 0] <= fu[-1]) & (uv[v, ..., 1] <= fv[-1])  # inside the map's centres
            assert inner.sum() > 50
            assert np.allclose(read[v][inner].numpy(), ref[inner.numpy()], atol=1e-2)


def test_targets_decode_back_to_the_boxes(item):
    g = _grid(item, cell=0.4, range_m=40.0)
    rows = positive_rows(item)
    t = bev_targets(item.boxes_3d, item.box_classes, rows, g, 2)
    assert sorted(t.rows.tolist()) == rows and float(t.heatmap.max()) == 1.0
    boxes = decode_regression(t.regression, t.cells, g)
    ref = item.boxes_3d[t.rows]
    assert torch.allclose(boxes[:, :2], ref[:, :2], atol=1e-4)  # the centre itself, not just its cell
    assert torch.allclose(boxes[:, 2:6], ref[:, 2:6], atol=1e-4)
    dyaw = torch.atan2(torch.sin(boxes[:, 6] - ref[:, 6]), torch.cos(boxes[:, 6] - ref[:, 6]))
    assert float(dyaw.abs().max()) < 1e-4
    for c, cell in zip(t.classes, t.cells):
        assert float(t.heatmap[c].view(-1)[cell]) == 1.0 and float(t.weight.view(-1)[cell]) == 1.0
    others = [r for r in range(len(item.boxes_3d)) if r not in rows]
    if others:  # road users outside the ground truth are ignored, not background
        iy, ix = g.cell_of(item.boxes_3d[others, :2])
        inside = g.inside(iy, ix)
        assert bool((t.weight[iy[inside], ix[inside]] == 0).all())


def test_the_heading_survives_a_box_turned_by_180_degrees(item):
    """Issue 87 item 2: the state holds which way a road user faces, not only its axis: a box turned by 180 degrees
    has the same axis targets and the other direction, decoding to the turned heading, and the results file and its
    reader keep it (the devkit's AOE compares headings over the full circle)."""
    from dataset_spec.nuscenes_format import quaternion_yaw, yaw_quaternion

    g = _grid(item, cell=0.4, range_m=40.0)
    rows = positive_rows(item)
    turned = item.boxes_3d.clone()
    turned[:, 6] = turned[:, 6] + math.pi
    a, b = (bev_targets(boxes, item.box_classes, rows, g, 2) for boxes in (item.boxes_3d, turned))
    assert torch.allclose(a.regression[:, 6:8], b.regression[:, 6:8], atol=1e-5)  # one axis
    assert torch.equal(a.regression[:, 8], -b.regression[:, 8])  # the other way along it
    yaw = decode_regression(b.regression, b.cells, g)[:, 6]
    d = yaw - turned[b.rows, 6]
    assert float(torch.atan2(torch.sin(d), torch.cos(d)).abs().max()) < 1e-4
    for y in (0.3, 0.3 + math.pi, -2.5):
        back = quaternion_yaw(yaw_quaternion(y))
        assert abs(math.atan2(math.sin(back - y), math.cos(back - y))) < 1e-9


def test_boxes_projected_into_the_views_equal_the_labels(item):
    rows = positive_rows(item)
    boxes = item.boxes_3d[rows].numpy().astype(np.float64)
    dets = WorldDetections(boxes, np.linspace(0.9, 0.5, len(rows)), item.box_classes[rows].numpy())
    views = project_into_views(dets, item, item.scored)
    for v in item.scored:
        gt = item.gt[v]
        for j, row in enumerate(gt.object_rows):
            k = rows.index(int(row))
            hit = np.where(np.isclose(views[v].centres, boxes[k, :3]).all(axis=1))[0]
            assert len(hit) == 1, (v, row)
            assert np.abs(views[v].boxes[hit[0]] - gt.boxes[j]).max() < 1.0
            assert abs(views[v].distances[hit[0]] - gt.distances[j]) < 1e-6
        assert len(views[v].boxes) == len(gt.object_rows), "no detection a label threshold would reject"


def test_late_fusion_of_a_car_with_its_copy_equals_projecting_it_once(item):
    rows = positive_rows(item)
    dets = WorldDetections(item.boxes_3d[rows].numpy().astype(np.float64), np.linspace(0.9, 0.4, len(rows)),
                           item.box_classes[rows].numpy())
    once = project_into_views(dets, item, item.scored)
    twice = project_into_views(pool_cars([dets, dets], [1, 2], radius=1.0), item, item.scored)
    for a, b in zip(once, twice):
        assert np.array_equal(a.boxes, b.boxes) and np.array_equal(a.scores, b.scores)
    moved = WorldDetections(dets.boxes + [[3.0, 0, 0, 0, 0, 0, 0]], dets.scores * 0.5, dets.classes)
    assert len(centre_nms(WorldDetections.concat([dets, moved]), 1.0)) == 2 * len(dets)


def test_hungarian_finds_the_minimum_cost_assignment():
    rng = np.random.default_rng(0)
    for n, m in ((3, 3), (2, 5), (6, 4)):
        cost = rng.uniform(0, 10, (n, m))
        pairs = hungarian(cost)
        if n <= m:
            best = min(sum(cost[i, p[i]] for i in range(n)) for p in itertools.permutations(range(m), n))
        else:
            best = min(sum(cost[p[j], j] for j in range(m)) for p in itertools.permutations(range(n), m))
        assert len(pairs) == min(n, m) and len({i for i, _ in pairs}) == len({j for _, j in pairs}) == min(n, m)
        assert math.isclose(sum(cost[i, j] for i, j in pairs), best)


def _det(xy, scores, classes):
    xy = np.asarray(xy, float).reshape(-1, 2)
    return ViewDetections(np.zeros((len(xy), 4)), np.asarray(scores, float), np.asarray(classes, int),
                          centres=np.c_[xy, np.zeros(len(xy))])


def _gt(xy, classes, visible=None):
    xy = np.asarray(xy, float).reshape(-1, 2)
    return ViewGroundTruth(np.zeros((len(xy), 4)), np.asarray(classes, int),
                           None if visible is None else np.asarray(visible, float), np.ones(len(xy), bool),
                           centres=np.c_[xy, np.zeros(len(xy))], excluded_centres=np.zeros((0, 3)))


def test_centre_distance_ap_and_moda_on_hand_computed_cases():
    names = ["car", "pedestrian"]
    gt = _gt([[0, 0], [10, 0]], [0, 0], visible=[1.0, 0.0])
    # one car found 0.3 m off, one 3 m off; a false positive far away, scored lowest
    det = _det([[0.3, 0], [13, 0], [50, 50]], [0.9, 0.8, 0.1], [0, 0, 0])
    m = metrics_3d([(det, gt)], names)
    ap = m["per_view"]["ap"]  # the nuScenes devkit's own calc_ap
    # recall 0.5 with precision 1 up to it: nuScenes AP = mean over recall points 0.11..1 of max(p - 0.1, 0) / 0.9,
    # the devkit's linear interpolation taking at recall 0.50 itself the last detection's precision there (1/3)
    assert ap["0.5"]["car"] == pytest.approx((39 * 0.9 + (1 / 3 - 0.1)) / 0.9 / 90)
    assert ap["4"]["car"] == pytest.approx((89 * 0.9 + (2 / 3 - 0.1)) / 0.9 / 90)  # both before the false positive
    assert "pedestrian" not in ap["0.5"]  # no ground truth of the class: not in the means
    assert m["counts"] == {"tp": 1, "fp": 2, "fn": 1} and m["moda"] == pytest.approx(1 - 3 / 2)
    assert m["modp"] == pytest.approx(1 - 0.3 / 1.0)
    assert m["recall_within_1m"]["fully hidden in the target view"] == {"recall": 0.0, "n": 1}
    none = metrics_3d([(_det([], [], []), gt)], names)
    assert none["moda"] == 0.0 and none["per_view"]["ap"]["1"]["car"] == 0.0 and none["modp"] is None
    empty = metrics_3d([(det, _gt([], []))], names)
    assert empty["moda"] is None and empty["per_view"]["ap"]["1"]["mean"] is None
    no_3d = ViewDetections(np.zeros((1, 4)), np.ones(1), np.zeros(1, int))
    assert metrics_3d([(no_3d, gt)], names) is None
    ped = metrics_3d([(_det([[0.6, 0]], [0.9], [1]), _gt([[0, 0]], [1]))], names)
    assert ped["counts"]["tp"] == 0, "pedestrians match within 0.5 m only"


def test_equal_neighbouring_peaks_are_taken_in_flat_index_order_as_the_convention_says():
    """INT8 heatmaps make neighbouring values equal (33 of 99 peaks tied): both are peaks, the one of lower flat index
    (class, row, column) first, and centre NMS keeps it."""
    from pnyolo.components.bev_grid import BevGrid
    from pnyolo.decoding.world import heatmap_detections

    heat = torch.full((2, 4, 4), -10.0)
    heat[1, 2, 1] = heat[1, 2, 2] = 2.0  # class 1: two equal neighbours
    heat[0, 0, 3] = 2.0  # class 0, the same score
    reg = torch.zeros(9, 4, 4)
    reg[7] = reg[8] = 1.0  # yaw 0: axis 0, facing along it
    grid = BevGrid(0.0, 0.0, 1.0, 4, 4)
    both = heatmap_detections(heat, reg, grid, threshold=0.5)
    assert both.classes.tolist() == [0, 1, 1] and both.boxes[1:, 0].tolist() == [1.0, 2.0]  # flat order
    merged = heatmap_detections(heat, reg, grid, threshold=0.5, nms_m=1.5)
    assert merged.classes.tolist() == [0, 1] and merged.boxes[1, 0] == 1.0  # the lower index kept


def test_boxes_go_into_views_on_the_device_as_a_labelled_road_user_would():
    """Issue 64, item 3: every detection and view at once in torch, against dataset_spec's numpy rule per box."""
    from dataset_spec import LabelThresholds
    from dataset_spec.boxes import box_in_view, frustum_fraction, points_in_box
    from pnyolo.data.frame import frame_item
    from pnyolo.data.item import ViewCamera
    from pnyolo.decoding.detections import WorldDetections
    from pnyolo.decoding.world import project_into_views
    from pnyolo.config import load_config

    rng = np.random.default_rng(4)
    W, H = 64, 48
    K = np.array([[W * 0.8, 0, W / 2 - 0.5], [0, W * 0.8, H / 2 - 0.5], [0, 0, 1.0]])
    cams = []
    for v in range(3):
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = [[0, 0, 1.0], [-1, 0, 0], [0, -1, 0]], [0.0, 2.0 * v, 1.5]
        cams.append((K, c2w))
    cfg = load_config(None, tiny("model.kind=bev"))
    item, _ = frame_item([np.zeros((H, W, 3), np.uint8)] * 3, cams, cfg.data, ["car", "pedestrian"])
    thresholds = LabelThresholds(max_distance=30.0, per_class={"pedestrian": {"min_in_frame": 0.5}})
    item.cameras = [ViewCamera(0.3, 25.0, (2 * W, 2 * H), thresholds) for _ in range(3)]  # renders twice the size
    P = 300
    boxes = np.column_stack([rng.uniform(-8, 40, P), rng.uniform(-15, 15, P), rng.uniform(0, 2, P),
                             rng.uniform(0.5, 5, (P, 3)), rng.uniform(-np.pi, np.pi, P)])
    boxes[0, :3] = [0.0, 2.0, 1.5]  # a box holding camera 1: its own car
    dets = WorldDetections(boxes, rng.uniform(0, 1, P), rng.integers(0, 2, P))
    got = project_into_views(dets, item, [0, 1])
    assert len(got[2].scores) == 0  # not a view to fill
    for v in (0, 1):
        K64, c2w = item.K[v].double().numpy(), item.camera_to_world[v].double().numpy()
        kept, ref_boxes = [], []
        for p in range(P):
            cx, cy, cz, length, width, height, yaw = boxes[p]
            if points_in_box(c2w[None, :3, 3], (cx, cy, cz), (length, width, height), yaw)[0]:
                continue
            seen = box_in_view(K64, c2w, W, H, 0.3, 25.0, (cx, cy, cz), (length, width, height), yaw)
            if seen is None:
                continue
            t = thresholds.for_class(["car", "pedestrian"][dets.classes[p]])
            w_px, h_px = (seen[0][2] - seen[0][0]) / 0.5, (seen[0][3] - seen[0][1]) / 0.5
            if seen[1] > t.max_distance or min(w_px, h_px) < t.min_box_pixels:
                continue
            if frustum_fraction(K64, c2w, (cx, cy, cz), (length, width, height), yaw, W, H, 0.3) < t.min_in_frame:
                continue
            kept.append(p)
            ref_boxes.append(seen[0])
        assert len(kept) > 20 and (v != 1 or 0 not in kept)  # camera 1's own car is never in its view
        np.testing.assert_array_equal(got[v].centres, boxes[kept, :3])
        np.testing.assert_allclose(got[v].boxes, np.reshape(ref_boxes, (-1, 4)), atol=1e-9)


def test_late_fusion_s_steps_alone_what_a_receiver_pools_and_a_channel_that_changes_nothing(item):
    """Issue 66: the steps of late fusion tested one by one. Each car reports one road user of its own; a
    receiver pools them all, or, keeping its own detector (``others_only``), all but its own car's; a channel
    without pose noise or senders hands the cars' detections on untouched."""
    from pnyolo.cooperation.late_fusion import Channel, received_pool
    from pnyolo.cooperation.pose_noise import PoseNoise, car_of

    cars = []
    for b in range(3):
        box = np.array([[5.0 * b, 3.0, 0.8, 4.0, 1.8, 1.5, 0.0]])
        cars.append(WorldDetections(box, np.array([0.9]), np.array([0])))
    everyone = received_pool(item, cars, 0, None, 1.0, None)
    assert sorted(everyone.boxes[:, 0].tolist()) == [0.0, 5.0, 10.0]
    others = received_pool(item, cars, 0, None, 1.0, None, others_only=True)
    kept = {float(x) for x in others.boxes[:, 0]}
    assert kept == {5.0 * b for b in range(3) if car_of(item, b) != car_of(item, 0)} and 0.0 not in kept
    assert not Channel().noisy
    assert Channel(PoseNoise(0.2, 0.2, 0)).noisy and not Channel(PoseNoise(0.0, 0.0, 0)).noisy


def test_late_fusion_is_a_function_of_the_cars_messages_alone(item):
    """Issue 77, item 3: no model, no device: the cars' messages in, each view's detections out. On-time messages
    pool by the best car; a late one moves to the item's time by the velocity it carries; the bytes are the
    messages'."""
    import dataclasses

    from pnyolo.cooperation.late_fusion import LateRule, car_id, late_fusion, sent_bytes
    from pnyolo.cooperation.message import CarMessage, message_bytes

    rows = positive_rows(item)
    truth = WorldDetections(item.boxes_3d[rows].numpy().astype(np.float64), np.linspace(0.9, 0.4, len(rows)),
                            item.box_classes[rows].numpy())
    now = item.frame / (item.fps or 1.0)
    messages = [CarMessage(car_id(item, b), now, (0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0),
                           truth if b == 0 else WorldDetections.empty()) for b in range(len(item.views))]
    rule = LateRule(send=0.3, keep=None, calibration=None, radius=1.0)
    got = late_fusion(messages, item, rule)
    want = project_into_views(truth, item, item.scored)
    for v in item.scored:
        assert np.array_equal(got[v].boxes, want[v].boxes) and np.array_equal(got[v].scores, want[v].scores)
    assert sent_bytes(messages) == message_bytes(len(truth)) + (len(messages) - 1) * message_bytes(0)
    # the same road users sent 0.5 s ago from 2 m/s behind in x: moved to now, they stand where they are now
    behind = truth.boxes.copy()
    behind[:, 0] -= 1.0
    late = dataclasses.replace(messages[0], timestamp=now - 0.5,
                               detections=WorldDetections(behind, truth.scores, truth.classes),
                               velocities=np.tile([2.0, 0.0], (len(truth), 1)),
                               velocity_covariances=np.zeros((len(truth), 3)))
    moved = late_fusion([late, *messages[1:]], item, rule)
    for v in item.scored:
        np.testing.assert_allclose(moved[v].boxes, want[v].boxes, atol=1e-9)


def test_the_heading_is_an_axis_and_a_direction_over_the_whole_circle():
    """Every heading round the circle encodes to (sin 2 yaw, cos 2 yaw, front) and decodes back; the axis alone is
    what a symmetric footprint shows (a yaw and yaw + pi share it), the front says which of the two."""
    from pnyolo.components.heading import decode_heading, heading_targets

    yaws = torch.linspace(-math.pi, math.pi, 73)[:-1] + 1e-3
    enc = torch.tensor([heading_targets(float(y)) for y in yaws])
    back = decode_heading(enc[:, 0], enc[:, 1], enc[:, 2])
    d = back - yaws
    assert float(torch.atan2(torch.sin(d), torch.cos(d)).abs().max()) < 1e-5
    turned = torch.tensor([heading_targets(float(y) + math.pi) for y in yaws])
    assert torch.allclose(turned[:, :2], enc[:, :2], atol=1e-5) and torch.equal(turned[:, 2], -enc[:, 2])
