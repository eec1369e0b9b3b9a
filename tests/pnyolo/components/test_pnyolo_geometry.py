"""Torch camera math against the numpy contract, and projection round trips."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from dataset_spec import Dataset
from dataset_spec import camera as npcam
from dataset_spec.boxes import points_in_box
from dataset_spec.synthetic import toy_scenario
from pnyolo.components import geometry as g
from pnyolo.components.ray_samplers import sample_along_rays

torch.set_num_threads(2)


def _cams(width=64, height=48):
    scn = toy_scenario(width=width, height=height)
    K = torch.tensor(np.stack([c.K for c in scn.cameras]), dtype=torch.float64)
    T = torch.tensor(np.stack([c.camera_to_world for c in scn.cameras]), dtype=torch.float64)
    return scn, K, T


def test_torch_matches_numpy_projection_and_rays():
    scn, K, T = _cams()
    rng = np.random.default_rng(0)
    pts = rng.uniform(-10, 10, (50, 3))
    for v, cam in enumerate(scn.cameras):
        uv_np, z_np = npcam.project_points(cam.K, cam.camera_to_world, pts)
        uv_t, z_t = g.project_points(K[v], T[v], torch.tensor(pts))
        front = z_np > 1e-3
        np.testing.assert_allclose(uv_t.numpy()[front], uv_np[front], rtol=1e-9, atol=1e-6)
        np.testing.assert_allclose(z_t.numpy(), z_np, atol=1e-9)
        pix = rng.uniform(0, 60, (20, 2))
        o_np, d_np = npcam.pixel_rays(cam.K, cam.camera_to_world, pix)
        o_t, d_t = g.pixel_rays(K[v], T[v], torch.tensor(pix))
        np.testing.assert_allclose(o_t.numpy(), o_np, atol=1e-12)
        np.testing.assert_allclose(d_t.numpy(), d_np, atol=1e-12)
    np.testing.assert_allclose(g.invert_rigid(T).numpy(), np.stack([npcam.invert_rigid(c.camera_to_world) for c in scn.cameras]),
                               atol=1e-12)


def test_point_on_cell_ray_projects_back_to_its_cell():
    scn, K, T = _cams()
    gh, gw, W, H = 6, 8, 64, 48
    uv = g.grid_cell_centres(gh, gw, W, H, dtype=torch.float64)
    for v in range(3):
        o, d = g.pixel_rays(K[v], T[v], uv.reshape(-1, 2))
        for t in (1.0, 5.0, 13.0):
            pts = o + t * d
            uv_all, _, z, valid = g.project_to_views(K, T, pts, W, H)
            assert valid[v].all() and (z[v] > 0).all()
            np.testing.assert_allclose(uv_all[v].numpy(), uv.reshape(-1, 2).numpy(), atol=1e-6)
            cells = g.pixel_to_cell(uv_all[v], gh, gw, W, H)
            rows, cols = torch.meshgrid(torch.arange(gh), torch.arange(gw), indexing="ij")
            assert torch.equal(cells, torch.stack([rows, cols], -1).reshape(-1, 2))


def test_points_behind_camera_and_outside_image_are_flagged():
    scn, K, T = _cams()
    c2w = T[0]
    fwd, eye = c2w[:3, 2], c2w[:3, 3]
    behind = eye - 5 * fwd  # straight behind: would project to the principal point if not flagged
    ahead = eye + 5 * fwd
    side = eye + 5 * c2w[:3, 0] + 0.1 * fwd  # far off to the right, in front
    _, _, z, valid = g.project_to_views(K[:1], T[:1], torch.stack([behind, ahead, side]), 64, 48)
    assert valid[0].tolist() == [False, True, False]
    assert z[0, 0] < 0


def test_rays_through_segmentation_pixels_hit_the_objects_3d_box(synthetic_dataset):
    ds = Dataset.open(synthetic_dataset)
    name = ds.scenario_names()[0]
    scn = ds.scenario(name)
    for cam in scn.cameras:
        inst = ds.read_instance(name, cam.name)
        depth = ds.read_depth(name, cam.name)
        K = torch.tensor(cam.K)
        T = torch.tensor(cam.camera_to_world)
        for actor in scn.actors[1:]:
            vs, us = np.nonzero(inst == actor.id)
            if len(us) == 0:
                continue
            o, d = g.pixel_rays(K, T, torch.tensor(np.stack([us, vs], -1), dtype=torch.float64))
            # the planar depth of the pixel along the unit ray: t = depth / (d . camera z)
            t = torch.tensor(depth[vs, us], dtype=torch.float64) / (d @ T[:3, 2])
            pts = (o + t[:, None] * d).numpy()
            assert points_in_box(pts, actor.box.center, actor.box.size, actor.box.yaw, margin=1e-3).all()


def test_slab_clipping_keeps_samples_between_ground_and_cap():
    scn, K, T = _cams()
    uv = g.grid_cell_centres(12, 16, 64, 48, dtype=torch.float64).reshape(-1, 2)
    o, d = g.pixel_rays(K[0], T[0], uv)
    t, ok = sample_along_rays(o, d, 32, 1.0, 13.0, slab=(0.0, 3.0))
    z = (o[:, None] + t[..., None] * d[:, None])[..., 2]
    assert ((z[ok] >= -1e-9) & (z[ok] <= 3 + 1e-9)).all()
    assert (t[ok] >= 1 - 1e-9).all() and (t[ok] <= 13 + 1e-9).all()
    t_plain, _ = sample_along_rays(o, d, 32, 1.0, 13.0)
    z_plain = (o[:, None] + t_plain[..., None] * d[:, None])[..., 2]
    assert ((z_plain < 0) | (z_plain > 3)).any()  # plain sampling wastes samples below the road


@pytest.mark.parametrize("stratified", [False, True])
def test_samples_sorted_within_bounds(stratified):
    o = torch.zeros(5, 3)
    d = torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    t, ok = sample_along_rays(o, d, 16, 1.0, 13.0, stratified=stratified)
    assert ok.all() and (t.diff(dim=1) > 0).all() and t.min() >= 1 and t.max() <= 13


def _segmentation_rays_hit_boxes(actors, inst, depth, K, camera_to_world, to_world=(1.0, 1.0, 1.0)) -> int:
    """Rays of the camera (K, camera_to_world) through each actor's pixels of an instance image, taken
    to the pixel's depth (along the optical axis) and scaled per axis by ``to_world``, land inside
    the actor's 3D box. Returns how many actors the image shows."""
    K, T = K.double(), camera_to_world.double()
    seen = 0
    for actor in actors:
        vs, us = np.nonzero(inst == actor.id)
        if len(us) == 0:
            continue
        o, d = g.pixel_rays(K, T, torch.tensor(np.stack([us, vs], -1), dtype=torch.float64))
        t = torch.tensor(depth[vs, us].copy(), dtype=torch.float64) / (d @ T[:3, 2])
        pts = (o + t[:, None] * d).numpy() * np.asarray(to_world)
        assert points_in_box(pts, actor.box.center, actor.box.size, actor.box.yaw, margin=2e-3).all()
        seen += 1
    return seen


def test_mirrored_item_is_a_consistent_mirrored_world(tmp_path):
    """Flip augmentation: every image flipped, every camera mirrored, labels flipped, and the
    mirrored cameras' rays through the flipped segmentation still hit each object's (mirrored) box."""
    from test_pnyolo_common import make_dataset, small_config

    from pnyolo.data.dataset import Draw, MultiViewDataset

    root = make_dataset(tmp_path / "ds")
    mvd = MultiViewDataset(root, None, small_config(**{"data.hflip": "true"}), training=True,
                           scenarios=Dataset.open(root).scenario_names())
    scenario, variant = mvd.items[0].scenario, mvd.items[0].variant
    plain, mirrored = (mvd.load(scenario, variant, [0, 1, 2], draw=Draw(mirror=m)) for m in (False, True))
    assert not plain.mirrored and mirrored.mirrored
    torch.testing.assert_close(mirrored.images, plain.images.flip(-1))
    width = plain.grid.width
    ds = Dataset.open(root)
    scn = ds.scenario(scenario)
    hits = 0
    for v, cam in enumerate(scn.cameras[:3]):
        gp, gm = plain.gt[v].boxes, mirrored.gt[v].boxes
        assert len(gp) > 0
        np.testing.assert_allclose(gm, np.stack([width - 1 - gp[:, 2], gp[:, 1], width - 1 - gp[:, 0], gp[:, 3]], 1))
        inst = ds.read_instance(scenario, cam.name)[:, ::-1]
        depth = ds.read_depth(scenario, cam.name)[:, ::-1]
        hits += _segmentation_rays_hit_boxes(scn.actors[1:], inst, depth, mirrored.K[v], mirrored.camera_to_world[v],
                                             to_world=[-1.0, 1.0, 1.0])  # back to the original world
    assert hits >= 3
    for v, cam in enumerate(scn.cameras[:3]):  # every labelled road user is ground truth or excluded from it
        labels = ds.read_labels(scenario, cam.name)
        gt = mirrored.gt[v]
        assert len(gt.boxes) + len(gt.excluded_boxes) == sum(o.cls in mvd.class_names for o in labels.objects)
    # the YOLO targets hold the same objects, mirrored: same cells' rows and anchors, x mirrored
    from pnyolo.models import build_model

    targets = build_model(mvd.cfg, len(mvd.class_names)).targets  # the kind builds them from the ground truth
    tp, tm = targets(plain), targets(mirrored)
    assert int(tp[..., 0].sum()) == int(tm[..., 0].sum()) > 0
    torch.testing.assert_close(tm[..., 0], tp[..., 0].flip(2))


def test_shifted_views_keep_their_geometry_and_labels(tmp_path):
    """Shift augmentation: each view's image moved by its own whole-pixel offset, K's principal
    point moved with it; rays through the shifted segmentation still hit each object's box, boxes
    move by the same offset, and a box pushed mostly out of the frame leaves the ground truth."""
    from test_pnyolo_common import make_dataset, small_config

    from pnyolo.data.dataset import Draw, MultiViewDataset
    from pnyolo.data.augment import shift_image

    root = make_dataset(tmp_path / "ds")
    mvd = MultiViewDataset(root, None, small_config(**{"data.shift_px": "6"}), training=True,
                           scenarios=Dataset.open(root).scenario_names())
    scenario, variant = mvd.items[0].scenario, mvd.items[0].variant
    shifts = [(5, -3), (-6, 2), (0, 0)]
    plain = mvd.load(scenario, variant, [0, 1, 2], draw=Draw(mirror=False, shifts=[(0, 0)] * 3))
    moved = mvd.load(scenario, variant, [0, 1, 2], draw=Draw(mirror=False, shifts=shifts))
    assert moved.shifts == shifts
    width, height = plain.grid.width, plain.grid.height
    ds = Dataset.open(root)
    scn = ds.scenario(scenario)
    hits = 0
    for v, (cam, (dx, dy)) in enumerate(zip(scn.cameras[:3], shifts)):
        img = plain.images[v].permute(1, 2, 0).numpy()
        np.testing.assert_array_equal(moved.images[v].permute(1, 2, 0).numpy(), shift_image(img, dx, dy))
        gp, gm = plain.gt[v].boxes, moved.gt[v].boxes
        assert len(gp) > 0
        inside = [b + [dx, dy, dx, dy] for b in gp]  # the toy scene's boxes stay well inside the frame
        np.testing.assert_allclose(gm, np.clip(inside, [-0.5, -0.5, -0.5, -0.5],
                                               [width - 0.5, height - 0.5, width - 0.5, height - 0.5]))
        inst = shift_image(ds.read_instance(scenario, cam.name)[..., None], dx, dy)[..., 0]
        depth = shift_image(ds.read_depth(scenario, cam.name)[..., None], dx, dy)[..., 0]
        hits += _segmentation_rays_hit_boxes(scn.actors[1:], inst, depth, moved.K[v], moved.camera_to_world[v])
    assert hits >= 3
    # a shift larger than the image pushes every box out: nothing left but excluded boxes
    from pnyolo.models import build_model

    targets = build_model(mvd.cfg, len(mvd.class_names)).targets
    gone = mvd.load(scenario, variant, [0, 1, 2], draw=Draw(mirror=False, shifts=[(width, 0)] * 3))
    for v in range(3):
        assert len(gone.gt[v].boxes) == 0 and len(gone.gt[v].excluded_boxes) == len(plain.gt[v].boxes) + len(plain.gt[v].excluded_boxes)
        assert gone.images[v].abs().sum() == 0 and targets(gone)[v][..., 0].abs().sum() == 0  # none in frame
    # random shifts only in training and within data.shift_px
    for _ in range(5):
        assert all(max(abs(dx), abs(dy)) <= 6 for dx, dy in mvd[0].shifts)
    evaluation = MultiViewDataset(root, None, small_config(**{"data.shift_px": "6"}), training=False,
                                  scenarios=Dataset.open(root).scenario_names())
    assert evaluation[0].shifts == [(0, 0)] * 3
    # without a shift no random number is drawn: runs from before data.shift_px repeat exactly
    unshifted = MultiViewDataset(root, None, small_config(), training=True, scenarios=Dataset.open(root).scenario_names())
    state = torch.get_rng_state()
    assert unshifted.load(scenario, variant, [0, 1, 2], draw=Draw(mirror=False)).shifts == [(0, 0)] * 3
    assert torch.equal(torch.get_rng_state(), state)


def test_torch_cameras_are_the_twin_of_the_spec_camera():
    from dataset_spec import CameraInfo
    from dataset_spec.synthetic import look_at, simple_intrinsics
    from pnyolo.components.geometry import Cameras

    infos = [CameraInfo(f"c{k}", 160, 90, simple_intrinsics(160, 90), look_at(eye, (0.0, 0.0, 0.5)))
             for k, eye in enumerate([(3.0, -7.0, 1.4), (-6.0, 2.0, 2.0)])]
    cams = Cameras(torch.tensor(np.stack([c.K for c in infos])), torch.tensor(np.stack([c.camera_to_world for c in infos])),
                   160, 90)
    pts = np.random.default_rng(4).uniform(-2, 2, (30, 3))
    uv, _, depth, valid = cams.project(torch.tensor(pts))
    pix = torch.tensor([[10.0, 20.0], [80.0, 45.0], [159.0, 0.0]], dtype=torch.float64)
    origins, dirs = cams.pixel_rays(pix)
    for v, info in enumerate(infos):
        ref_uv, ref_z = info.project(pts)
        inside = (ref_z > 1e-3) & (ref_uv[:, 0] >= -0.5) & (ref_uv[:, 0] <= 159.5) & (ref_uv[:, 1] >= -0.5) \
            & (ref_uv[:, 1] <= 89.5)
        assert np.array_equal(valid[v].numpy(), inside) and inside.sum() > 5
        np.testing.assert_allclose(uv[v].numpy()[inside], ref_uv[inside], atol=1e-9)
        np.testing.assert_allclose(depth[v].numpy(), ref_z, atol=1e-9)
        ref_o, ref_d = info.pixel_rays(pix.numpy())
        np.testing.assert_allclose(origins[v].numpy(), ref_o, atol=1e-9)
        np.testing.assert_allclose(dirs[v].numpy(), ref_d, atol=1e-9)
