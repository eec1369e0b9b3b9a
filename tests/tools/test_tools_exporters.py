"""Exporters: each format is read back and gives the same boxes; format rules hold."""
from __future__ import annotations

import importlib.util
import json
import shutil

import numpy as np
import pytest
import yaml

from dataset_spec import Box3D, CameraInfo, Dataset
from dataset_spec.camera import project_points
from dataset_spec.synthetic import look_at, simple_intrinsics
from tools.exporters import export_coco, export_kitti, export_pixelnerf, export_yolo
from tools.exporters.coco import box_from_coco, read_coco, rle_decode, rle_encode
from tools.exporters.kitti import box_from_kitti, kitti_3d, kitti_box, read_kitti_labels
from tools.exporters.pixelnerf import read_pixelnerf_scene
from tools.exporters.yolo import read_yolo_labels
from tools.projection import label_dataset


@pytest.fixture(scope="module")
def labelled(synthetic_dataset, tmp_path_factory):
    root = shutil.copytree(synthetic_dataset, tmp_path_factory.mktemp("exp") / "ds")
    label_dataset(root, progress=False)
    return Dataset.open(root)


def kept_by_stem(ds: Dataset) -> dict[str, tuple]:
    out = {}
    for name in ds.scenario_names():
        for cam in ds.scenario(name).cameras:
            out[f"{name}__{cam.name}"] = (name, cam, ds.read_labels(name, cam.name).kept())
    return out


def split_of(ds, scenario):
    return next(s for s, names in ds.info.splits.items() if scenario in names)


# ----------------------------------------------------------------------------- YOLO
def test_yolo_export_round_trips_and_follows_ultralytics_rules(labelled, tmp_path):
    out = export_yolo(labelled, tmp_path / "yolo")
    data = yaml.safe_load((out / "data.yaml").read_text())
    assert data["names"] == {0: "car", 1: "pedestrian"} and data["nc"] == 2
    assert {data["train"], data["val"], data["test"]} == {"images/train", "images/val", "images/test"}
    n_boxes = 0
    for stem, (scn, cam, kept) in kept_by_stem(labelled).items():
        split = split_of(labelled, scn)
        assert (out / "images" / split / f"{stem}.png").is_file()
        label_file = out / "labels" / split / f"{stem}.txt"
        for line in label_file.read_text().splitlines():
            cols = line.split()
            assert len(cols) == 5 and int(cols[0]) < data["nc"]
            assert all(0.0 <= float(v) <= 1.0 for v in cols[1:])
        classes, boxes = read_yolo_labels(label_file, cam.width, cam.height)
        assert classes.tolist() == [labelled.info.detectable_classes.index(o.cls) for o in kept]
        assert np.allclose(boxes, [o.box for o in kept], atol=1e-4 * cam.width)
        n_boxes += len(kept)
    assert n_boxes > 10


def _ultralytics_requirements(path):
    """What Ultralytics' check_det_dataset requires of data.yaml (FACTS: train and val keys, names/nc
    agreeing, every val path existing), checked without Ultralytics (it would pull numpy 2)."""
    data = yaml.safe_load(path.read_text())
    for key in ("train", "val"):
        assert data.get(key), f"'{key}:' key missing"
    assert len(data["names"]) == data["nc"]
    for key in ("train", "val", "test"):
        if data.get(key):
            assert (path.parent / data[key]).is_dir() and any((path.parent / data[key]).iterdir()), key
    return data


def test_yolo_export_has_every_key_ultralytics_needs_when_a_split_is_empty(labelled, tmp_path):
    ds = Dataset.open(shutil.copytree(labelled.root, tmp_path / "ds"))
    names = ds.scenario_names()
    ds.set_splits({"train": names, "val": [], "test": []})
    out = export_yolo(ds, tmp_path / "yolo")
    data = _ultralytics_requirements(out / "data.yaml")
    assert data["val"] == data["train"] == "images/train" and "test" not in data
    assert "no val images" in (out / "data.yaml").read_text()  # says what it did
    ds.set_splits({"train": [], "val": names[:1], "test": names[1:]})
    data = _ultralytics_requirements(export_yolo(ds, tmp_path / "yolo2") / "data.yaml")
    assert (data["train"], data["val"], data["test"]) == ("images/val", "images/val", "images/test")


@pytest.mark.skipif(importlib.util.find_spec("ultralytics") is None,
                    reason="ultralytics is not installed (kept out of the environment: it needs numpy 2)")
def test_yolo_export_passes_ultralytics_own_checker(labelled, tmp_path):  # pragma: no cover - optional
    from ultralytics.data.utils import check_det_dataset

    ds = Dataset.open(shutil.copytree(labelled.root, tmp_path / "ds"))
    ds.set_splits({"train": ds.scenario_names(), "val": [], "test": []})
    data = check_det_dataset(str(export_yolo(ds, tmp_path / "yolo") / "data.yaml"), autodownload=False)
    assert data["nc"] == 2


def test_yolo_all_variants_become_images(labelled, tmp_path):
    out = export_yolo(labelled, tmp_path / "yolo", variant="all")
    images = sorted(p.name for p in (out / "images").rglob("*.png"))
    assert len(images) == 9 * 2 and any(n.endswith("__dusk.png") for n in images)
    labels = list((out / "labels").rglob("*.txt"))
    assert len(labels) == len(images)


# ----------------------------------------------------------------------------- COCO
@pytest.mark.parametrize("seed", range(4))
def test_rle_round_trip(seed):
    rng = np.random.default_rng(seed)
    mask = rng.random((7 + seed, 5 + 2 * seed)) < [0.0, 0.3, 0.9, 1.0][seed]
    rle = rle_encode(mask)
    assert sum(rle["counts"]) == mask.size and rle["size"] == list(mask.shape)
    assert np.array_equal(rle_decode(rle), mask)


def test_rle_is_column_major_and_starts_with_background():
    mask = np.array([[1, 0], [1, 1]], bool)  # column-major: 1 1 0 1
    assert rle_encode(mask)["counts"] == [0, 2, 1, 1]


def test_coco_export_round_trips_with_amodal_and_visible_masks(labelled, tmp_path):
    out = export_coco(labelled, tmp_path / "coco")
    stems = kept_by_stem(labelled)
    n_ann = n_hidden = 0
    for split in ("train", "val", "test"):
        doc = read_coco(out / "annotations" / f"instances_{split}.json")
        assert [c["name"] for c in doc["categories"]] == ["car", "pedestrian"]
        images = {im["id"]: im for im in doc["images"]}
        assert len(images) == len(doc["images"])
        for ann in doc["annotations"]:
            im = images[ann["image_id"]]
            scn, cam, kept = stems[im["file_name"][:-4]]
            assert (out / "images" / split / im["file_name"]).is_file()
            label = next(o for o in labelled.read_labels(scn, cam.name).objects if o.instance_id == ann["instance_id"])
            # left out by the thresholds: an ignore region
            assert ann["iscrowd"] == (label.instance_id not in {o.instance_id for o in kept})
            assert np.allclose(box_from_coco(ann["bbox"]), label.box)
            visible, amodal = rle_decode(ann["visible_segmentation"]), rle_decode(ann["segmentation"])
            assert np.array_equal(visible, labelled.read_instance(scn, cam.name) == label.instance_id)
            assert ann["visible_area"] == label.visible_pixels == visible.sum()
            assert ann["area"] == label.amodal_pixels == amodal.sum() > 0  # the amodal mask: the real size
            assert (visible & ~amodal).sum() <= 0.05 * visible.sum() + 2  # what is seen lies on the silhouette
            assert ann["category_id"] == labelled.info.class_id(label.cls)
            n_ann += not ann["iscrowd"]
            n_hidden += label.visible_fraction == 0 and not ann["iscrowd"]
    assert n_ann == sum(len(k) for _, _, k in stems.values()) and n_hidden > 0


@pytest.mark.skipif(importlib.util.find_spec("pycocotools") is None, reason="pycocotools is not installed")
def test_coco_export_loads_in_pycocotools(labelled, tmp_path):  # pragma: no cover - optional dependency
    from pycocotools import mask as mask_utils
    from pycocotools.coco import COCO

    from pycocotools.cocoeval import COCOeval

    out = export_coco(labelled, tmp_path / "coco")
    coco = COCO(str(out / "annotations" / "instances_train.json"))
    anns = coco.loadAnns(coco.getAnnIds())
    for ann in anns:
        assert np.array_equal(coco.annToMask(ann).astype(bool), rle_decode(ann["segmentation"]))
        assert mask_utils.area(mask_utils.frPyObjects(ann["segmentation"], *ann["segmentation"]["size"])) == ann["area"]
    # the ground truth scored against itself: AP 1, ignore regions and hidden road users included
    dets = [{"image_id": a["image_id"], "category_id": a["category_id"], "bbox": a["bbox"], "score": 1.0}
            for a in anns if not a["iscrowd"]]
    ev = COCOeval(coco, coco.loadRes(dets), "bbox")
    ev.evaluate(), ev.accumulate()
    ev.summarize()
    assert ev.stats[0] == pytest.approx(1.0)


# ----------------------------------------------------------------------------- KITTI
def test_kitti_export_round_trips_2d_and_3d(labelled, tmp_path):
    out = export_kitti(labelled, tmp_path / "kitti")
    n = n_dont_care = 0
    for stem, (scn, cam, kept) in kept_by_stem(labelled).items():
        split = split_of(labelled, scn)
        parsed = read_kitti_labels(out / split / "label_2" / f"{stem}.txt")
        assert (out / split / "calib" / f"{stem}.txt").read_text().startswith("P0: ")
        objects = [o for o in parsed if o["type"] != "DontCare"]
        dont_care = [o for o in parsed if o["type"] == "DontCare"]
        left_out = [o for o in labelled.read_labels(scn, cam.name).left_out()]
        assert len(objects) == len(kept) and len(dont_care) == len(left_out)
        for obj in parsed:  # KITTI's image extent: pixel centres 0 .. W - 1, never our -0.5 edge
            assert 0 <= obj["left"] <= obj["right"] <= cam.width - 1 and 0 <= obj["top"] <= obj["bottom"] <= cam.height - 1
        for obj, label in zip(dont_care, left_out):  # ignore regions: the 2D box, KITTI's placeholders
            assert np.allclose([obj["left"], obj["top"], obj["right"], obj["bottom"]], kitti_box(label.box, cam),
                               atol=0.006)
            assert (obj["truncated"], obj["occluded"], obj["z"]) == (-1, -1, -1000)
        n_dont_care += len(dont_care)
        for obj, label in zip(objects, kept):
            assert obj["type"] == {"car": "Car", "pedestrian": "Pedestrian"}[label.cls]
            assert np.allclose([obj["left"], obj["top"], obj["right"], obj["bottom"]], kitti_box(label.box, cam),
                               atol=0.006)
            assert obj["occluded"] == label.occlusion_level
            assert obj["truncated"] == pytest.approx(1 - label.in_frame_fraction, abs=0.006)
            actor = labelled.scenario(scn).actor(label.instance_id).box
            back = box_from_kitti(cam, obj)
            assert np.allclose(back.center, actor.center, atol=2e-3) and np.allclose(back.size, actor.size, atol=1e-3)
            assert abs(np.angle(np.exp(1j * (back.yaw - actor.yaw)))) < 1e-3
            assert obj["alpha"] == pytest.approx(np.angle(np.exp(1j * (obj["rotation_y"] - np.arctan2(obj["x"], obj["z"])))),
                                                 abs=2e-3)
            n += 1
    assert n > 10 and n_dont_care > 0
    cam = next(iter(kept_by_stem(labelled).values()))[1]  # a box clipped at the image's edges: KITTI's extent
    assert kitti_box([-0.5, -0.5, cam.width - 0.5, cam.height - 0.5], cam) == (0, 0, cam.width - 1, cam.height - 1)


def test_kitti_rotation_y_follows_kitti_convention_for_a_level_camera():
    cam = CameraInfo("c", 64, 48, simple_intrinsics(64, 48), look_at((0, 0, 1), (10, 0, 1)))  # looks along +X
    # Camera right is world -Y. Facing the camera's right -> ry = 0; facing the camera -> ry = +pi/2.
    right = kitti_3d(cam, Box3D(np.array([10.0, 0, 1]), np.array([4.0, 2, 2]), -np.pi / 2))
    towards = kitti_3d(cam, Box3D(np.array([10.0, 0, 1]), np.array([4.0, 2, 2]), np.pi))
    assert right["rotation_y"] == pytest.approx(0.0, abs=1e-9)
    assert towards["rotation_y"] == pytest.approx(np.pi / 2)
    assert (right["x"], right["y"], right["z"]) == pytest.approx((0.0, 1.0, 10.0))  # bottom centre, y down


def _devkit_box_2d(obj: dict, calib: dict) -> np.ndarray | None:
    """A KITTI label's 2D box rebuilt as the KITTI object devkit does (corners in the object frame,
    rotated by rotation_y about y, moved to x y z, projected with P2); None when a corner lies
    closer than 0.1 m, where the devkit gives up too. Written from KITTI's definition, not ours."""
    h, w, l = obj["h"], obj["w"], obj["l"]
    corners = np.array([[l / 2, l / 2, -l / 2, -l / 2, l / 2, l / 2, -l / 2, -l / 2],
                        [0, 0, 0, 0, -h, -h, -h, -h],
                        [w / 2, -w / 2, -w / 2, w / 2, w / 2, -w / 2, -w / 2, w / 2]])
    c, s = np.cos(obj["rotation_y"]), np.sin(obj["rotation_y"])
    rect = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ corners + np.array([[obj["x"]], [obj["y"]], [obj["z"]]])
    if rect[2].min() < 0.1:
        return None
    uvw = calib["P2"].reshape(3, 4) @ np.vstack([rect, np.ones(8)])
    uv = uvw[:2] / uvw[2]
    return np.array([uv[0].min(), uv[1].min(), uv[0].max(), uv[1].max()])


def _read_calib(path) -> dict:
    return {k: np.array([float(v) for v in rest.split()]) for k, rest in
            (line.split(":", 1) for line in path.read_text().splitlines() if line.strip())}


def test_kitti_boxes_rebuilt_the_devkit_way_match_the_2d_box_for_pitched_cameras(tmp_path):
    """R0_rect levels the camera, so a box rebuilt upright in the rectified frame (as KITTI tools
    do) projects onto the label's 2D box, though the cameras look down a few degrees."""
    from dataset_spec.boxes import box_iou, clip_box_to_image, project_box_2d
    from tools.exporters.kitti import calib_text

    calib_file = tmp_path / "calib.txt"
    rng = np.random.default_rng(0)
    n = 0
    for pitch_deg, yaw_deg in ((4.0, 0.0), (2.5, 30.0), (-3.0, 100.0), (0.0, 200.0)):
        target = np.array([np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg)), 0.0])
        eye = np.array([0.0, 0.0, 1.5])
        cam = CameraInfo("c", 320, 180, simple_intrinsics(320, 180, 60.0),
                         look_at(eye, eye + 10 * target - [0, 0, 10 * np.tan(np.radians(pitch_deg))]))
        calib_file.write_text(calib_text(cam))
        calib = _read_calib(calib_file)
        r0 = calib["R0_rect"].reshape(3, 3)
        assert np.allclose(r0 @ r0.T, np.eye(3), atol=1e-9) and (pitch_deg != 0) == (not np.allclose(r0, np.eye(3)))
        for _ in range(12):
            along, across = rng.uniform(6, 35), rng.uniform(-8, 8)
            centre = eye + along * target + across * np.array([-target[1], target[0], 0.0])
            size = np.array([4.2, 1.8, 1.5]) if rng.random() < 0.5 else np.array([0.6, 0.6, 1.8])
            box = Box3D(np.array([centre[0], centre[1], size[2] / 2]), size, rng.uniform(-np.pi, np.pi))
            ours = project_box_2d(cam.K, cam.camera_to_world, box.corners, near=0.1)
            ours = None if ours is None else clip_box_to_image(ours, cam.width, cam.height)
            if ours is None:
                continue
            theirs = _devkit_box_2d(kitti_3d(cam, box), calib)
            theirs = clip_box_to_image(theirs, cam.width, cam.height)
            assert box_iou(ours[None], theirs[None])[0, 0] >= 0.99, (pitch_deg, yaw_deg, ours, theirs)
            n += 1
    assert n >= 30


# ----------------------------------------------------------------------------- pixelNeRF
def test_pixelnerf_export_round_trips(labelled, tmp_path):
    out = export_pixelnerf(labelled, tmp_path / "pn")
    for split in ("train", "val", "test"):
        assert (out / f"{split}.lst").read_text().split() == labelled.info.splits[split]
    scn = labelled.scenario("toy_01")
    scene = read_pixelnerf_scene(out / "toy_01")
    assert scene["views"] == [0, 1, 2] and np.allclose(scene["K"], scn.cameras[0].K)
    pts = np.array([[0.0, 0.0, 0.5], [3.0, 2.0, 1.0], [-2.0, 4.0, 0.2]])
    for i, cam in enumerate(scn.cameras):
        # World-to-camera in Blender axes: the camera looks down -z and y is up.
        p = pts @ scene["extrinsics"][i][:3, :3].T + scene["extrinsics"][i][:3, 3]
        assert np.all(p[:, 2] < 0)
        uv = np.stack([p[:, 0] / -p[:, 2], -p[:, 1] / -p[:, 2]], 1) @ cam.K[:2, :2].T + cam.K[:2, 2]
        assert np.allclose(uv, project_points(cam.K, cam.camera_to_world, pts)[0])
        kept = labelled.read_labels("toy_01", cam.name).kept()
        boxes = scene["boxes"][i]
        assert boxes[:, 0].tolist() == [{"pedestrian": 0, "car": 1}[o.cls] for o in kept]
        from dataset_spec.boxes import yolo_to_box

        back = np.array([yolo_to_box(b[1:], cam.width, cam.height) for b in boxes]).reshape(-1, 4)
        assert np.allclose(back, [o.box for o in kept], atol=1e-4 * cam.width)


# ----------------------------------------------------------------------------- CLI
def test_cli_exports_every_format(labelled, tmp_path, capsys):
    from tools.projection_cli import main

    assert main([str(labelled.root), "--no-labelling", "--export", "yolo,coco,kitti,pixelnerf", "--out",
                 str(tmp_path / "x"), "--quiet"]) == 0
    assert (tmp_path / "x/yolo/data.yaml").is_file() and (tmp_path / "x/coco/annotations/instances_val.json").is_file()
    assert (tmp_path / "x/kitti/test/label_2").is_dir() and (tmp_path / "x/pixelnerf/train.lst").is_file()
    assert main([str(labelled.root), "--no-labelling", "--export", "yolo", "--out", str(tmp_path / "y"),
                 "--variant", "sunset"]) == 2
    err = capsys.readouterr().err.strip()
    assert "sunset" in err and len(err.splitlines()) == 1
    assert json.loads(json.dumps(read_coco(tmp_path / "x/coco/annotations/instances_val.json")))  # plain JSON
