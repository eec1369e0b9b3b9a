"""Projection tool: silhouettes, visible / in-frame fractions, boxes, thresholds, CLI."""
from __future__ import annotations

import json
import time

import cv2
import numpy as np
import pytest

from dataset_spec import Actor, Box3D, CameraInfo, Dataset, DatasetInfo, LabelThresholds, LightingVariant, Scenario
from dataset_spec.boxes import box_iou
from dataset_spec.camera import points_to_camera, project_camera_points, world_to_camera
from dataset_spec.synthetic import BOX_FACES, look_at, raycast, simple_intrinsics
from tools.projection import label_dataset, label_scenario, label_view, measure_view
from tools.silhouette import clip_triangles_near, rasterise_mask

W, H = 160, 120


def car(aid, center, size=(4.0, 2.0, 2.0), yaw=0.0, cls="car", name=None):
    return Actor(aid, name or f"a{aid}", cls, Box3D(np.array(center, float), np.array(size, float), yaw))


def camera(name="cam", eye=(0.0, -10.0, 1.0), target=(0.0, 0.0, 1.0), width=W, height=H, **kw):
    return CameraInfo(name, width, height, simple_intrinsics(width, height), look_at(eye, target), **kw)


def build_dataset(root, actors, cameras, meshes=True) -> Dataset:
    """A one-scenario dataset whose instance maps are ray cast exactly (no ground: ids start at 2)."""
    ds = Dataset.create(root, DatasetInfo(name="handmade"))
    scn = Scenario("scene", actors, cameras, [LightingVariant("noon", "noon.exr")])
    if meshes:
        for a in actors:
            a.mesh = ds.write_mesh(scn.name, a.id, a.box.corners, BOX_FACES)
    ds.write_scenario(scn)
    for cam in cameras:
        depth, inst, shade = raycast(scn, cam)
        ds.write_depth(scn.name, cam.name, depth)
        ds.write_instance(scn.name, cam.name, inst)
        ds.write_rgb(scn.name, cam.name, "noon", (np.stack([shade] * 3, -1) * 255).astype(np.uint8))
    ds.set_splits({"train": [scn.name], "val": [], "test": []})
    return ds


def by_id(view_labels):
    return {o.instance_id: o for o in view_labels.objects}


def hull_fractions(K, c2w, corners, width, height, pad):
    """Independent reference: in-image / total pixel centres inside the convex hull of projected
    corners (the silhouette of a box entirely in front of the camera)."""
    uv = project_camera_points(K, points_to_camera(c2w, corners)).astype(np.float32)
    hull = cv2.convexHull(uv)
    v, u = np.mgrid[-pad:height + pad, -pad:width + pad]
    inside = np.array([cv2.pointPolygonTest(hull, (float(x), float(y)), False) >= 0
                       for x, y in zip(u.ravel(), v.ravel())]).reshape(u.shape)
    in_img = inside[pad:pad + height, pad:pad + width]
    return in_img.sum() / inside.sum(), in_img.sum()


# ----------------------------------------------------------------------------- rasteriser
def _point_in_triangles(tris, pts):
    def cross(p, q, r):
        return (q[0] - p[0]) * (r[:, 1] - p[1]) - (q[1] - p[1]) * (r[:, 0] - p[0])

    hit = np.zeros(len(pts), bool)
    for a, b, c in tris:
        d1, d2, d3 = cross(a, b, pts), cross(b, c, pts), cross(c, a, pts)
        hit |= ((d1 >= 0) & (d2 >= 0) & (d3 >= 0)) | ((d1 <= 0) & (d2 <= 0) & (d3 <= 0))
    return hit


def test_rasterised_mask_matches_brute_force_point_in_triangle():
    rng = np.random.default_rng(3)
    tris = rng.uniform(-15, 55, size=(25, 3, 2))
    mask = rasterise_mask(tris, 40, 30)
    v, u = np.mgrid[0:30, 0:40]
    ref = _point_in_triangles(tris, np.stack([u.ravel(), v.ravel()], 1).astype(float)).reshape(30, 40)
    assert mask.sum() > 100 and (mask != ref).sum() == 0


@pytest.mark.parametrize("third_z, n_out", [(2.0, 2), (0.3, 1)])
def test_near_clipping_matches_ray_triangle_intersection(third_z, n_out):
    """A pixel is in the clipped silhouette iff its ray meets the triangle at z >= near."""
    K = simple_intrinsics(48, 36)
    tri = np.array([[[-3.0, -1.0, -2.0], [2.0, -0.5, 6.0], [0.5, 2.0, third_z]]])  # vertex 0 behind the camera
    near = 0.5
    clipped, src = clip_triangles_near(tri, near)
    assert len(clipped) == n_out and np.all(src == 0) and np.all(clipped[..., 2] >= near - 1e-12)
    mask = rasterise_mask(project_camera_points(K, clipped), 48, 36)
    v, u = np.mgrid[0:36, 0:48]
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1).reshape(-1, 3)
    a, b, c = tri[0]
    n = np.cross(b - a, c - a)
    t = (n @ a) / (d @ n)  # ray o=0, point = t d, planar depth z = t
    p = t[:, None] * d
    bary = np.linalg.lstsq(np.stack([b - a, c - a], 1), (p - a).T, rcond=None)[0].T
    ref = (t >= near) & (bary[:, 0] >= -1e-9) & (bary[:, 1] >= -1e-9) & (bary.sum(1) <= 1 + 1e-9)
    assert ref.sum() > 50
    assert (mask.ravel() != ref).sum() <= 2  # ties on edges only


def _volume_share(K, c2w, box, width, height, near, n=200_000):
    """Independent reference: the share of uniformly random points of the box that are in view."""
    from dataset_spec.boxes import yaw_rotation

    pts = np.random.default_rng(0).uniform(-0.5, 0.5, (n, 3)) * box.size @ yaw_rotation(box.yaw).T + box.center
    cam = points_to_camera(c2w, pts)
    front = cam[:, 2] >= near
    uv = project_camera_points(K, np.where(front[:, None], cam, 1.0))
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= height - 0.5)
    return float((front & inside).mean())


@pytest.mark.parametrize("center,size,yaw", [
    ((8.5, 2.0, 1.0), (4.0, 2.0, 2.0), 0.0),            # straddling the right image border
    ((2.8, -10.0, 1.5), (12.0, 2.5, 3.0), np.pi / 2),   # a bus beside the camera, half of it behind
    ((0.0, -10.05, 1.5), (2.0, 0.5, 1.0), 0.0),         # cut by the near plane, in frame sideways
    ((0.0, -16.0, 1.0), (4.0, 2.0, 2.0), 0.0),          # behind the camera
    ((0.0, 0.0, 1.0), (4.0, 2.0, 2.0), 0.3)])           # wholly in view
def test_in_frame_fraction_is_the_share_of_the_box_in_the_view_frustum(center, size, yaw):
    from dataset_spec.boxes import frustum_fraction

    K, c2w = simple_intrinsics(W, H), look_at((0, -10, 1.5), (0, 0, 1.5))
    box = Box3D(np.array(center, float), np.array(size, float), yaw)
    got = frustum_fraction(K, c2w, box.center, box.size, box.yaw, W, H, near=0.1)
    assert got == pytest.approx(_volume_share(K, c2w, box, W, H, 0.1), abs=0.01)


# ----------------------------------------------------------------------------- hand-made scenes
@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Camera at y=-10 looking +y. 2: car half behind a wall (3, 'other'); 4: car straddling the
    right image border; 5: car behind the camera; 6: pedestrian partly behind the camera plane, close
    on the left."""
    actors = [car(2, (0, 0, 1)), car(3, (-5, -5, 2), size=(10, 0.2, 4), cls="other", name="wall"),
              car(4, (8.5, 2, 1)), car(5, (0, -16, 1)), car(6, (-1.0, -9.5, 1), size=(0.6, 2.0, 1.8),
                                                             cls="pedestrian")]
    cams = [camera("front"), camera("side", eye=(12, 0, 1.5), target=(0, 0, 1))]
    ds = build_dataset(tmp_path_factory.mktemp("hand") / "ds", actors, cams)
    return ds, {vl.camera: by_id(vl) for vl in label_scenario(ds, "scene", write=True)}


def test_half_hidden_car_has_visible_fraction_one_half(scene):
    _, labels = scene
    half = labels["front"][2]
    assert abs(half.visible_fraction - 0.5) < 0.05
    assert half.occlusion_level == 1 and half.in_frame_fraction == 1.0
    assert half.visible_pixels > 100
    assert 3 not in labels["front"]  # the wall occludes but is not labelled
    assert labels["side"][2].visible_fraction > 0.97  # seen from the side, nothing hides it


def test_border_straddling_car_gets_the_in_frame_share_of_its_box(scene):
    ds, labels = scene
    lab = labels["front"][4]
    cam = ds.scenario("scene").camera("front")
    box = ds.scenario("scene").actor(4).box
    ref_fraction = _volume_share(cam.K, cam.camera_to_world, box, W, H, cam.near)
    _, ref_pixels = hull_fractions(cam.K, cam.camera_to_world, box.corners, W, H, pad=40)
    assert 0.2 < ref_fraction < 0.8
    assert abs(lab.in_frame_fraction - ref_fraction) < 0.01
    assert abs(lab.amodal_pixels - ref_pixels) <= 3
    assert lab.visible_fraction > 0.97  # truncation is not occlusion
    assert lab.box[2] == W - 0.5 and lab.box[0] > W / 2  # clipped at the right border


def test_a_bus_beside_the_camera_gets_the_share_of_it_in_frame(tmp_path):
    """The regression of a silhouette-based in-frame fraction: a bus alongside the camera, from 4 m
    behind it to 8 m ahead, crosses the near plane and fills a third of the image, fully visible.
    Its image-plane silhouette is unbounded (the old measure gave about 3e-4 and dropped it)."""
    bus = car(2, (2.6, -8.0, 1.5), size=(12.0, 2.5, 3.0), yaw=np.pi / 2)
    cam = camera("front", eye=(0, -10, 1.5), target=(0, 0, 1.5))
    ds = build_dataset(tmp_path / "ds", [bus], [cam])
    lab = by_id(label_view(ds, "scene", "front"))[2]
    assert lab.amodal_pixels > 0.3 * W * H and lab.visible_fraction > 0.97
    assert lab.in_frame_fraction == pytest.approx(_volume_share(cam.K, cam.camera_to_world, bus.box, W, H, cam.near),
                                                  abs=0.01)
    assert 0.3 < lab.in_frame_fraction < 0.45  # about a third of the bus is in the picture
    assert [o.instance_id for o in label_view(ds, "scene", "front").kept()] == [2]  # ground truth at min_in_frame 0.25


def test_actor_behind_camera_gets_no_label_and_partly_behind_one_no_wrapped_box(scene):
    ds, labels = scene
    assert 5 not in labels["front"]
    # 6 reaches 1.5 m in front of the camera, left of it: its box must not wrap to the right.
    lab = labels["front"][6]
    assert lab.box[0] == -0.5 and lab.box[2] < (W - 1) / 2 and 0.0 < lab.in_frame_fraction < 1.0
    assert lab.visible_fraction > 0.97 and lab.amodal_pixels > 100


def test_fully_visible_car_segmentation_box_inside_amodal_box(scene):
    ds, labels = scene
    lab = labels["side"][2]
    inst = ds.read_instance("scene", "side")
    ys, xs = np.nonzero(inst == 2)
    seg_centres = np.array([xs.min(), ys.min(), xs.max(), ys.max()], float)
    seg_edges = seg_centres + [-0.5, -0.5, 0.5, 0.5]
    assert np.all(seg_centres[:2] >= lab.box[:2]) and np.all(seg_centres[2:] <= lab.box[2:])
    assert box_iou(seg_edges, lab.box)[0, 0] >= 0.8
    assert np.allclose(lab.extras["silhouette_box"], seg_edges)  # mesh silhouette = ray-cast segmentation


def test_label_box_agrees_with_cv2_project_points(scene):
    ds, labels = scene
    scn = ds.scenario("scene")
    cam = scn.camera("side")
    w2c = world_to_camera(cam.camera_to_world)
    rvec, _ = cv2.Rodrigues(w2c[:3, :3])
    uv, _ = cv2.projectPoints(scn.actor(2).box.corners, rvec, w2c[:3, 3], cam.K, None)
    uv = uv.reshape(-1, 2)
    expected = [uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()]
    assert np.allclose(labels["side"][2].box, expected, atol=1e-6)


def test_distance_and_mesh_free_fallback(tmp_path):
    actors = [car(2, (1, 0, 1)), car(3, (-3, 4, 1), yaw=0.7)]
    ds_mesh = build_dataset(tmp_path / "a", actors, [camera()], meshes=True)
    ds_box = build_dataset(tmp_path / "b", [car(2, (1, 0, 1)), car(3, (-3, 4, 1), yaw=0.7)], [camera()], meshes=False)
    with_mesh, without = by_id(label_view(ds_mesh, "scene", "cam")), by_id(label_view(ds_box, "scene", "cam"))
    for i in (2, 3):
        assert without[i].extras["silhouette_source"] == "box" and with_mesh[i].extras["silhouette_source"] == "mesh"
        assert without[i].amodal_pixels == with_mesh[i].amodal_pixels > 0
    assert with_mesh[2].distance == pytest.approx(np.linalg.norm([1, 10, 0]))


def test_camera_mount_car_is_not_labelled(tmp_path):
    actors = [car(2, (0, -10, 1)), car(3, (0, 5, 1))]
    cam = camera(eye=(0.0, -8.0, 2.5), target=(0, 5, 1), mounted_on=2)
    labels = by_id(label_view(build_dataset(tmp_path / "ds", actors, [cam]), "scene", "cam"))
    assert 2 not in labels and 3 in labels


# ----------------------------------------------------------------------------- whole datasets
def test_label_dataset_writes_valid_labels_with_thresholds(synthetic_dataset, tmp_path):
    import shutil

    from dataset_spec.validate import validate

    root = shutil.copytree(synthetic_dataset, tmp_path / "ds")
    t = LabelThresholds(min_in_frame=0.3, per_class={"pedestrian": {"max_distance": 14.0}})
    assert label_dataset(root, t, progress=False) == 9
    assert [p for p in validate(root) if p.severity == "error"] == []
    ds = Dataset.open(root)
    vl = ds.read_labels("toy_01", "cam_0")
    assert vl.thresholds == t and len(vl.objects) >= 4
    assert all(o.cls in ("car", "pedestrian") for o in vl.objects)
    inst = ds.read_instance("toy_01", "cam_0")
    for o in vl.objects:  # every visible pixel lies inside the amodal box
        ys, xs = np.nonzero(inst == o.instance_id)
        if xs.size:
            assert o.box[0] <= xs.min() and xs.max() <= o.box[2] and o.box[1] <= ys.min() and ys.max() <= o.box[3]
    peds = [o for o in vl.objects if o.cls == "pedestrian"]
    assert all((o in vl.kept()) == (o.distance <= 14.0 and o.in_frame_fraction >= 0.3) for o in peds)
    assert len(vl.kept(LabelThresholds(min_visible=0.99))) < len(vl.objects)  # re-applied without relabelling


def test_measure_view_is_fast_for_50_actors():
    rng = np.random.default_rng(0)
    actors = [car(i + 2, (rng.uniform(-15, 15), rng.uniform(5, 40), 0.8), yaw=rng.uniform(-3, 3)) for i in range(50)]
    cam = camera(eye=(0, -5, 1.5), target=(0, 10, 1), width=640, height=480)
    meshes = {a.id: (a.box.corners, BOX_FACES) for a in actors}
    inst = np.zeros((480, 640), np.uint16)
    measure_view(cam, actors, meshes, inst, {"car"})  # warm-up
    start = time.perf_counter()
    labels = measure_view(cam, actors, meshes, inst, {"car"})
    assert time.perf_counter() - start < 1.0
    assert len(labels) > 30


# ----------------------------------------------------------------------------- CLI
def test_cli_labels_and_reports(synthetic_dataset, tmp_path, capsys):
    import shutil

    from tools.projection_cli import main

    root = shutil.copytree(synthetic_dataset, tmp_path / "ds")
    assert main([str(root), "--min-in-frame", "0.5", "--class-option", "pedestrian:max_distance=40,min_visible=0.1",
                 "--quiet"]) == 0
    stored = json.loads((root / "scenarios/toy_02/views/cam_1/labels.json").read_text())["thresholds"]
    assert stored["min_in_frame"] == 0.5 and stored["per_class"] == {"pedestrian": {"max_distance": 40.0,
                                                                                    "min_visible": 0.1}}


@pytest.mark.parametrize("args, needle", [
    (["NOT_A_DATASET"], "not a dataset folder"),
    (["{root}", "--class-option", "bicycle:max_distance=3"], "unknown class"),
    (["{root}", "--class-option", "car:speed=3"], "option must be one of"),
    (["{root}", "--min-in-frame", "1.5"], "not within [0, 1]"),
    (["{root}", "--export", "voc"], "unknown format"),
])
def test_cli_errors_are_one_line(synthetic_dataset, tmp_path, capsys, args, needle):
    from tools.projection_cli import main

    args = [a.format(root=synthetic_dataset) if a != "NOT_A_DATASET" else str(tmp_path) for a in args]
    try:
        rc = main(args)
    except SystemExit as exc:  # argparse type errors exit from the parser
        rc = exc.code
    err = capsys.readouterr().err
    assert rc == 2 and needle in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
