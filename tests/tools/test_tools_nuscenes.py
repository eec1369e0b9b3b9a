"""The nuScenes export, read by the official devkit (nuscenes-devkit 1.2.0): the tables load, the devkit's own
projection of every box agrees with our 2D labels, the pseudo-LiDAR's points fall exactly on the road users some
camera sees, a sequence's annotations chain along the track ids, and the devkit draws a camera with its boxes."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dataset_spec import Dataset
from dataset_spec.nuscenes_format import SPLIT_NAMES, VERSION, scene_name, token
from dataset_spec.synthetic import write_synthetic_dataset
from tools.exporters.nuscenes import channel
from tools.projection import label_dataset
from tools.projection_cli import main as labels_main

nuscenes = pytest.importorskip("nuscenes")
from nuscenes.nuscenes import NuScenes  # noqa: E402
from nuscenes.utils.geometry_utils import view_points  # noqa: E402


@pytest.fixture(scope="module", params=[1, 4], ids=["still", "sequence"])
def exported(request, tmp_path_factory):
    root = tmp_path_factory.mktemp(f"nusc{request.param}")
    ds = write_synthetic_dataset(root / "ds", n_scenarios=2, frames=request.param, fps=2.0)
    label_dataset(ds, progress=False)
    assert labels_main([str(ds), "--no-labelling", "--export", "nuscenes", "--variant", "all", "--out",
                        str(root / "exp"), "--quiet"]) == 0
    return Dataset.open(ds), NuScenes(version=VERSION, dataroot=str(root / "exp" / "nuscenes"), verbose=False)


def _actor_of(ds: Dataset, nusc, ann_token: str) -> tuple[str, str, int]:
    """(scenario, variant, actor id) of an annotation (its instance token names them)."""
    instance = nusc.get("sample_annotation", ann_token)["instance_token"]
    for scenario in ds.scenario_names():
        for v in ds.scenario(scenario).lighting:
            for a in ds.scenario(scenario).actors:
                if token(scene_name(scenario, v.name), "instance", a.id) == instance:
                    return scenario, v.name, a.id
    raise KeyError(instance)


def _frame(nusc, sd_token: str) -> int:
    """The frame of a sample data record (its file's name ends in __fNNNN)."""
    return int(nusc.get("sample_data", sd_token)["filename"].rsplit("__f", 1)[1][:4])


def test_the_devkit_loads_every_table_and_a_scene_per_scenario_and_lighting(exported):
    ds, nusc = exported
    frames = ds.scenario(ds.scenario_names()[0]).frames
    scenes = sum(len(ds.scenario(s).lighting) for s in ds.scenario_names())
    assert len(nusc.scene) == scenes and len(nusc.sample) == scenes * frames
    cams = {c.name for s in ds.scenario_names() for c in ds.scenario(s).cameras}
    assert set(nusc.sample[0]["data"]) == {channel(c) for c in cams} | {"LIDAR_TOP"}
    assert channel("cam_0") == "CAM_0" and channel("front") == "CAM_FRONT" and channel("cam") == "CAM_CAM"
    assert {c["name"] for c in nusc.category} >= {"vehicle.car", "human.pedestrian.adult"}
    from nuscenes.utils.splits import get_scenes_of_split

    splits = {split: get_scenes_of_split(SPLIT_NAMES[split], nusc) for split in SPLIT_NAMES}  # the devkit's reader
    assert sorted(sum(splits.values(), [])) == sorted(s["name"] for s in nusc.scene)  # every scene in one split
    assert all(name.rsplit("__", 1)[0] in ds.split(split) for split, names in splits.items() for name in names)


def test_the_devkit_s_projection_of_every_box_is_our_label_box_within_a_pixel(exported):
    ds, nusc = exported
    compared = 0
    for sample in nusc.sample:
        for ch, sd_token in sample["data"].items():
            if not ch.startswith("CAM_"):
                continue
            _, boxes, K = nusc.get_sample_data(sd_token)
            frame = _frame(nusc, sd_token)
            for box in boxes:
                scenario, _, aid = _actor_of(ds, nusc, box.token)
                camera = next(c.name for c in ds.scenario(scenario).cameras if channel(c.name) == ch)
                label = next((o for o in ds.read_labels(scenario, camera, frame).objects if o.instance_id == aid), None)
                if label is None or not label.in_frame_fraction >= 1.0 or not (label.visible_fraction or 0) > 0:
                    continue  # visible and wholly in frame: the corners' bounds are the label's amodal box
                uv = view_points(box.corners(), K, normalize=True)[:2]
                mine = np.array([uv[0].min(), uv[1].min(), uv[0].max(), uv[1].max()])
                np.testing.assert_allclose(mine, label.box, atol=1.0)
                compared += 1
    assert compared > 10


def test_lidar_points_count_zero_exactly_for_the_road_users_no_camera_sees(exported):
    ds, nusc = exported
    unseen = seen = 0
    for ann in nusc.sample_annotation:
        scenario, _, aid = _actor_of(ds, nusc, ann["token"])
        sample = nusc.get("sample", ann["sample_token"])
        frame = _frame(nusc, sample["data"]["LIDAR_TOP"])
        pixels = [o.visible_pixels or 0 for c in ds.scenario(scenario).cameras
                  for o in ds.read_labels(scenario, c.name, frame).objects if o.instance_id == aid]
        assert (ann["num_lidar_pts"] == 0) == (sum(pixels) == 0), (scenario, aid, frame, pixels)
        unseen += ann["num_lidar_pts"] == 0
        seen += ann["num_lidar_pts"] > 0
    assert seen > 0
    pts = np.fromfile(nusc.get_sample_data_path(nusc.sample[0]["data"]["LIDAR_TOP"]), dtype=np.float32).reshape(-1, 5)
    assert len(pts) > 100 and np.isfinite(pts).all() and set(np.unique(pts[:, 4])) <= {0.0, 1.0, 2.0}
    # one sweep per scenario and frame, whatever the lighting: every variant's scene reads the same file
    sweeps = {nusc.get("sample_data", s["data"]["LIDAR_TOP"])["filename"] for s in nusc.sample}
    frames = sum(ds.scenario(s).frames for s in ds.scenario_names())
    assert len(sweeps) == frames < len(nusc.sample) and all((Path(nusc.dataroot) / f).is_file() for f in sweeps)


def test_a_sequence_s_annotations_chain_along_its_track_ids(exported):
    ds, nusc = exported
    for inst in nusc.instance:
        chain, tok = [], inst["first_annotation_token"]
        while tok:
            ann = nusc.get("sample_annotation", tok)
            assert ann["instance_token"] == inst["token"]
            chain.append(ann)
            tok = ann["next"]
        assert len(chain) == inst["nbr_annotations"] and chain[-1]["token"] == inst["last_annotation_token"]
        stamps = [nusc.get("sample", a["sample_token"])["timestamp"] for a in chain]
        assert stamps == sorted(stamps) and len(set(_actor_of(ds, nusc, a["token"]) for a in chain)) == 1


def test_the_devkit_draws_a_camera_with_its_boxes(exported, tmp_path):
    _, nusc = exported
    cam = next(v for k, v in nusc.sample[0]["data"].items() if k.startswith("CAM_"))
    nusc.render_sample_data(cam, out_path=str(tmp_path / "cam.png"), verbose=False)
    assert (tmp_path / "cam.png").stat().st_size > 5_000


def test_the_devkit_draws_a_sweep_over_the_scene_s_map_with_its_defaults(exported, tmp_path):
    """Issue 74, item 5: each scenario's map is its ground seen from above, in the export's global frame (our world
    moved so every camera and road user lies at least MAP_MARGIN_M inside it): the sweep's points on the ground
    fall on the map's foreground, those above it do not; render_sample_data draws a sweep over it with its
    defaults."""
    from nuscenes.utils.data_classes import LidarPointCloud
    from pyquaternion import Quaternion

    from dataset_spec.nuscenes_format import MAP_MARGIN_M

    ds, nusc = exported
    assert len(nusc.map) == len(ds.scenario_names()) and all(m["filename"].endswith(".png") for m in nusc.map)
    assert all(min(a["translation"][:2]) >= MAP_MARGIN_M for a in nusc.sample_annotation)
    for sample in nusc.sample:
        sd = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
        pose = nusc.get("ego_pose", sd["ego_pose_token"])
        points = LidarPointCloud.from_file(str(Path(nusc.dataroot) / sd["filename"])).points[:3]
        world = Quaternion(pose["rotation"]).rotation_matrix @ points + np.array(pose["translation"])[:, None]
        log = nusc.get("log", nusc.get("scene", sample["scene_token"])["log_token"])
        mask = nusc.get("map", log["map_token"])["mask"]
        low, high = world[:, world[2] < 0.05], world[:, world[2] > 1.0]
        assert mask.is_on_mask(low[0], low[1], dilation=0.3).mean() > 0.9
        assert mask.is_on_mask(high[0], high[1]).mean() < 0.5
    lidar = nusc.sample[0]["data"]["LIDAR_TOP"]
    nusc.render_sample_data(lidar, out_path=str(tmp_path / "lidar.png"), verbose=False)  # underlay_map=True
    assert (tmp_path / "lidar.png").stat().st_size > 5_000


def test_a_camera_dataset_without_depth_is_refused_in_one_line(tmp_path, capsys):
    root = write_synthetic_dataset(tmp_path / "ds", n_scenarios=1)
    label_dataset(root, progress=False)
    info = json.loads((root / "dataset.json").read_text())
    info["absent"] = ["depth"]
    (root / "dataset.json").write_text(json.dumps(info))
    assert labels_main([str(root), "--no-labelling", "--export", "nuscenes", "--out", str(tmp_path / "x")]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pseudo-LiDAR needs depth" in err[0] and not (tmp_path / "x").exists()


def test_cameras_named_as_nuscenes_channels_are_what_mmdetection3d_s_converter_reads(tmp_path, capsys):
    """Issue 74, item 4: --nuscenes-channels exports the named cameras (at most six) as CAM_FRONT, CAM_FRONT_RIGHT,
    ... in mmdetection3d's order, and only those; each keeps its own ego pose and calibration (the devkit places
    every box in it as in the plain export), the LiDAR sweep and its prev chain unchanged; a camera a scenario
    lacks, a seventh or a repeated name is a one-line error before anything is written."""
    from dataset_spec.nuscenes_format import CAMERA_CHANNELS

    ds = write_synthetic_dataset(tmp_path / "ds", n_scenarios=2, frames=2, fps=2.0)
    label_dataset(ds, progress=False)
    cams = [c.name for c in Dataset.open(ds).scenario("toy_01").cameras]
    named = cams[::-1][:2]
    assert labels_main([str(ds), "--no-labelling", "--export", "nuscenes", "--nuscenes-channels", ",".join(named),
                        "--out", str(tmp_path / "six"), "--quiet"]) == 0
    assert labels_main([str(ds), "--no-labelling", "--export", "nuscenes", "--out", str(tmp_path / "all"),
                        "--quiet"]) == 0
    six = NuScenes(version=VERSION, dataroot=str(tmp_path / "six" / "nuscenes"), verbose=False)
    plain = NuScenes(version=VERSION, dataroot=str(tmp_path / "all" / "nuscenes"), verbose=False)
    for sample, ref in zip(six.sample, plain.sample):
        assert set(sample["data"]) == {*CAMERA_CHANNELS[:2], "LIDAR_TOP"}
        for camera, ch in zip(named, CAMERA_CHANNELS):
            _, boxes, k = six.get_sample_data(sample["data"][ch])
            _, want, k_ref = plain.get_sample_data(ref["data"][channel(camera)])
            assert np.allclose(k, k_ref) and [b.token for b in boxes] == [b.token for b in want]
            assert all(np.allclose(a.center, b.center) for a, b in zip(boxes, want))
        assert six.get("sample_data", sample["data"]["LIDAR_TOP"])["filename"] == \
            plain.get("sample_data", ref["data"]["LIDAR_TOP"])["filename"]
    for bad, words in (([cams[0], "nowhere"], "has no camera nowhere"), ([cams[0]] * 2, "different camera names"),
                       ([cams[0]] * 7, "1 to 6")):
        assert labels_main([str(ds), "--no-labelling", "--export", "nuscenes", "--nuscenes-channels", ",".join(bad),
                            "--out", str(tmp_path / "bad")]) != 0
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0] and not (tmp_path / "bad").exists()
    assert labels_main([str(ds), "--export", "coco", "--nuscenes-channels", cams[0], "--out", str(tmp_path / "c")]) != 0
    assert "goes with --export nuscenes" in capsys.readouterr().err
