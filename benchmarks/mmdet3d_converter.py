"""mmdetection3d's nuScenes converter run on our export (issue 74, item 4): its own ``get_available_scenes`` and
``_fill_trainval_infos`` from a checkout of mmdetection3d, on a nuScenes export whose cameras are named as
nuScenes' six channels (``project-labels --export nuscenes --nuscenes-channels ...``), the train and val scenes
read from the export's ``splits.json`` (the two lines of ``create_nuscenes_infos`` a user changes: the version
assertion and the split lists). mmcv, mmengine and mmdet3d are not installed here: the four mmengine helpers those
functions call are given plain equivalents and the two mmdet3d names they import a stand-in (the converter's own
name mapping is used only for classes we do not export).

    .venv/bin/python benchmarks/mmdet3d_converter.py --mmdet3d ~/src/mmdetection3d --export out/exp/nuscenes \
        --dataset out/dataset

Prints what the infos hold and checks it: one info per sample, the export's cameras (the six channels the converter
reads) each with its image, intrinsics and a sensor-to-LiDAR transform equal to where the project's own
scenario.json and frames.json put that camera (found by its image's bytes, not by the export's tables), the LiDAR
file of 5 float32 a point, boxes and velocities per annotation. The converter puts the test split's scenes into
its val infos (``*_infos_val.pkl``): it knows only train and val.
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


def _scenes(ds) -> dict[str, tuple[str, str]]:
    """Each exported scene's name -> (scenario, lighting variant) of the project's dataset."""
    from dataset_spec.nuscenes_format import scene_name

    return {scene_name(s, v.name): (s, v.name) for s in ds.scenario_names() for v in ds.scenario(s).lighting}


def _our_sensor2lidar(ds, scenes: dict, data_path: str, digests: dict) -> np.ndarray:
    """(4, 4) where the project's own scenario.json / frames.json put the camera whose image ``data_path`` is, in
    the frame of the sample's LiDAR (the first camera's car at that frame: box centre, x forward, z up). The camera
    is the one whose rendered image has the same bytes: nothing is read from the export's tables."""
    import hashlib

    scene, frame = Path(data_path).stem.rsplit("__f", 1)
    scenario, variant = scenes[scene]
    scn = ds.scenario_at(scenario, int(frame))
    if (scenario, variant, int(frame)) not in digests:
        digests[scenario, variant, int(frame)] = {
            hashlib.sha256(ds.layout.rgb(scenario, c.name, variant, int(frame)).read_bytes()).digest(): c
            for c in scn.cameras}
    cam = digests[scenario, variant, int(frame)][hashlib.sha256(Path(data_path).read_bytes()).digest()]
    box = scn.actor(scn.cameras[0].mounted_on).box if scn.cameras[0].mounted_on is not None else None
    lidar = np.eye(4)
    if box is not None:
        c, s = np.cos(box.yaw), np.sin(box.yaw)
        lidar[:3, :3], lidar[:3, 3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], box.center
    return np.linalg.inv(lidar) @ np.asarray(cam.camera_to_world, dtype=np.float64)


def check_infos(infos: list[dict], dataset: Path, channels: list[str]) -> float:
    """Checks the converter's infos against the project's own dataset; returns the largest placement error (metres
    or rotation-matrix entries). Raises AssertionError naming the first thing wrong."""
    from dataset_spec import Dataset

    ds = Dataset.open(dataset)
    scenes, digests, worst = _scenes(ds), {}, 0.0
    for info in infos:
        assert set(info["cams"]) == set(channels), sorted(info["cams"])
        for ch, cam in info["cams"].items():
            assert Path(cam["data_path"]).is_file() and np.asarray(cam["cam_intrinsic"]).shape == (3, 3)
            want = _our_sensor2lidar(ds, scenes, cam["data_path"], digests)
            error = max(float(np.abs(np.asarray(cam["sensor2lidar_translation"]) - want[:3, 3]).max()),
                        float(np.abs(np.asarray(cam["sensor2lidar_rotation"]) - want[:3, :3]).max()))
            assert error < 1e-4, f"{ch} of {cam['data_path']}: sensor2lidar off by {error:.3g} from the dataset"
            worst = max(worst, error)
        points = np.fromfile(info["lidar_path"], dtype=np.float32)
        assert points.size % 5 == 0 and len(info["gt_boxes"]) == len(info["gt_names"]) == len(info["gt_velocity"])
    return worst


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mmdet3d", type=Path, required=True, help="an mmdetection3d checkout")
    p.add_argument("--export", type=Path, required=True, help="a nuScenes export (the folder holding v1.0-occluded)")
    p.add_argument("--dataset", type=Path, required=True,
                   help="the project's dataset it was exported from (where the cameras are checked against)")
    args = p.parse_args(argv)
    from nuscenes.nuscenes import NuScenes

    from dataset_spec.nuscenes_format import SPLIT_NAMES, VERSION

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
    channels = sorted({s["channel"] for s in nusc.sensor if s["modality"] == "camera"})
    worst = check_infos(infos, args.dataset, channels)
    sweeps = sum(len(i["sweeps"]) for i in infos)
    print(f"mmdetection3d's converter on {args.export}: {len(available)} scenes available, {len(train_infos)} train "
          f"and {len(val_infos)} val/test infos (the test split's scenes among them: the converter knows only train "
          f"and val); every info has the export's cameras ({', '.join(channels)}), a LiDAR file of 5 float32 a "
          f"point, each camera where {args.dataset}'s scenario and frames put it in the first camera car's frame "
          f"(within {worst:.1e}), {sweeps} sweeps in all, "
          f"{sum(len(i['gt_boxes']) for i in infos)} boxes ({sum(int(i['valid_flag'].sum()) for i in infos)} with "
          f"LiDAR points)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
