"""mmdetection3d's nuScenes converter run on our export (issue 74, item 4): its own ``get_available_scenes`` and
``_fill_trainval_infos`` from a checkout of mmdetection3d, on a nuScenes export whose cameras are named as
nuScenes' six channels (``project-labels --export nuscenes --nuscenes-channels ...``), the train and val scenes
read from the export's ``splits.json`` (the two lines of ``create_nuscenes_infos`` a user changes: the version
assertion and the split lists). mmcv, mmengine and mmdet3d are not installed here: the four mmengine helpers those
functions call are given plain equivalents and the two mmdet3d names they import a stand-in (the converter's own
name mapping is used only for classes we do not export).

    .venv/bin/python benchmarks/mmdet3d_converter.py --mmdet3d ~/src/mmdetection3d --export out/exp/nuscenes

Prints what the infos hold and checks it: one info per sample, the six cameras each with its image, intrinsics and
sensor-to-LiDAR transform, the LiDAR file of 5 float32 a point, sweeps following the previous frames, boxes and
velocities per annotation.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import pickle
import sys
import types
from pathlib import Path

import numpy as np


def _stubs() -> None:
    """Plain stand-ins for the mmcv / mmengine / mmdet3d imports at the converter's top."""
    mmengine = types.ModuleType("mmengine")
    mmengine.track_iter_progress = lambda items: items
    mmengine.is_filepath = lambda p: isinstance(p, (str, Path))
    mmengine.dump = lambda obj, path: Path(path).write_bytes(pickle.dumps(obj))

    def check_file_exist(path, msg="file {} does not exist"):
        if not Path(path).is_file():
            raise FileNotFoundError(msg.format(path))
    mmengine.check_file_exist = check_file_exist
    convert_utils = types.ModuleType("mmdet3d.datasets.convert_utils")
    convert_utils.NuScenesNameMapping = {"vehicle.car": "car", "human.pedestrian.adult": "pedestrian",
                                         "vehicle.truck": "truck", "vehicle.bus.rigid": "bus"}
    structures = types.ModuleType("mmdet3d.structures")
    structures.points_cam2img = None
    for name, module in {"mmcv": types.ModuleType("mmcv"), "mmengine": mmengine,
                         "mmdet3d": types.ModuleType("mmdet3d"), "mmdet3d.datasets": types.ModuleType("mmdet3d.datasets"),
                         "mmdet3d.datasets.convert_utils": convert_utils, "mmdet3d.structures": structures}.items():
        sys.modules.setdefault(name, module)


def load_converter(checkout: Path):
    path = checkout / "tools" / "dataset_converters" / "nuscenes_converter.py"
    if not path.is_file():
        raise SystemExit(f"{checkout}: no tools/dataset_converters/nuscenes_converter.py (an mmdetection3d checkout?)")
    _stubs()
    spec = importlib.util.spec_from_file_location("nuscenes_converter", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _global(nusc, sd_token: str) -> np.ndarray:
    """(4, 4) a sample data record's sensor in the global frame, by the devkit's records (ego pose, calibration)."""
    from pyquaternion import Quaternion

    sd = nusc.get("sample_data", sd_token)
    out = np.eye(4)
    for rec in (nusc.get("ego_pose", sd["ego_pose_token"]), nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])):
        step = np.eye(4)
        step[:3, :3], step[:3, 3] = Quaternion(rec["rotation"]).rotation_matrix, rec["translation"]
        out = out @ step
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mmdet3d", type=Path, required=True, help="an mmdetection3d checkout")
    p.add_argument("--export", type=Path, required=True, help="a nuScenes export (the folder holding v1.0-occluded)")
    args = p.parse_args()
    from nuscenes.nuscenes import NuScenes

    from dataset_spec.nuscenes_format import CAMERA_CHANNELS, SPLIT_NAMES, VERSION

    conv = load_converter(args.mmdet3d)
    nusc = NuScenes(version=VERSION, dataroot=str(args.export), verbose=False)
    splits = json.loads((args.export / VERSION / "splits.json").read_text())  # instead of nuscenes.utils.splits
    available = conv.get_available_scenes(nusc)
    by_name = {s["name"]: s["token"] for s in available}
    train = {by_name[n] for n in splits[SPLIT_NAMES["train"]] if n in by_name}
    val = {by_name[n] for n in splits[SPLIT_NAMES["val"]] + splits[SPLIT_NAMES["test"]] if n in by_name}
    train_infos, val_infos = conv._fill_trainval_infos(nusc, train, val, test=False, max_sweeps=10)
    infos = train_infos + val_infos
    assert len(infos) == len(nusc.sample), (len(infos), len(nusc.sample))
    worst = 0.0
    for info in infos:
        assert set(info["cams"]) == set(CAMERA_CHANNELS), sorted(info["cams"])
        lidar = _global(nusc, nusc.get("sample", info["token"])["data"]["LIDAR_TOP"])
        for cam in info["cams"].values():
            assert Path(cam["data_path"]).is_file() and np.asarray(cam["cam_intrinsic"]).shape == (3, 3)
            # its sensor-to-LiDAR transform places the camera where its own car's ego pose puts it
            want = np.linalg.inv(lidar) @ _global(nusc, cam["sample_data_token"])
            worst = max(worst, float(np.abs(np.asarray(cam["sensor2lidar_translation"]) - want[:3, 3]).max()),
                        float(np.abs(np.asarray(cam["sensor2lidar_rotation"]) - want[:3, :3]).max()))
        points = np.fromfile(info["lidar_path"], dtype=np.float32)
        assert points.size % 5 == 0 and len(info["gt_boxes"]) == len(info["gt_names"]) == len(info["gt_velocity"])
    assert worst < 1e-4, worst
    sweeps = sum(len(i["sweeps"]) for i in infos)
    print(f"mmdetection3d's converter on {args.export}: {len(available)} scenes available, {len(train_infos)} train "
          f"and {len(val_infos)} val/test infos; every info has the six cameras ({', '.join(CAMERA_CHANNELS)}), a "
          f"LiDAR file of 5 float32 a point, each camera placed by its own car's ego pose (within {worst:.1e}), "
          f"{sweeps} sweeps in all, "
          f"{sum(len(i['gt_boxes']) for i in infos)} boxes ({sum(int(i['valid_flag'].sum()) for i in infos)} with "
          f"LiDAR points)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
