"""The dataset in nuScenes' format, for camera 3D detectors and cooperative-perception code that read it
(BEVFormer, BEVDet, PETR and mmdetection3d's converters; V2X-Sim) and for the official devkit::

    OUT/v1.0-occluded/<table>.json                 the 13 tables NuScenes(version, dataroot=OUT) loads
    OUT/samples/CAM_<CAMERA>/<scene>__f<frame>.png  each camera's image (one channel per camera of the rig)
    OUT/samples/LIDAR_TOP/<scenario>__f<frame>.pcd.bin  a pseudo-LiDAR sweep of the frame (``pseudo_lidar``), one
                                                    file for every lighting variant's scene (the same geometry)
    OUT/v1.0-occluded/splits.json                   {"occ_train": [scene, ...], "occ_val": ..., "occ_test": ...}: our
                                                    splits as the devkit's custom splits (its evaluations' eval_set)

One scene per scenario (or sequence) and lighting variant (``--variant``: the first, one, or all), a sample per
frame linked prev/next, an instance per road user (its actor id: the track over the frames). Every camera is a
channel of its own with its own ``ego_pose`` (the car carrying it, at that frame: box centre, x forward, z up;
the world for a camera on no car) and ``calibrated_sensor`` (the camera in that car's frame, OpenCV axes as
nuScenes' cameras have them, intrinsics K), so the devkit's global -> ego -> sensor transforms place every box
in every camera. ``LIDAR_TOP``'s ego is the first camera's car; its sensor sits at that ego's origin. Each
annotation: category from our class and the actor's kind (``dataset_spec.nuscenes_format``), visibility from
its most visible view at that frame, attribute from its motion, ``num_lidar_pts`` the sweep's points on it
(zero exactly when no camera sees it). Written through atomic writers, every image checked before the first
byte; tables sorted by token.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np

from dataset_spec import Dataset
from dataset_spec.atomic import atomic_write_bytes, atomic_write_text
from dataset_spec.cli_support import UserError
from dataset_spec.names import JoinedNames, below
from dataset_spec.nuscenes_format import (ATTRIBUTES, CAMERA_CHANNELS, LIDAR, MOVING_M_S, SPLIT_NAMES, VERSION,
                                          VISIBILITY, attribute_of, global_offset, category_of, matrix_quaternion, pose_of, sample_token,
                                          scene_name, timestamp_us, token, visibility_token, yaw_quaternion)

from .common import check_images, copy_file, export_variants
from .nuscenes_map import ground_map
from .pseudo_lidar import sweep

TABLES = ("category", "attribute", "visibility", "instance", "sensor", "calibrated_sensor", "ego_pose", "log",
          "scene", "sample", "sample_data", "sample_annotation", "map")


def channel(camera: str) -> str:
    """A camera's nuScenes channel: CAM_ and its name in capitals, a "cam" the name starts with not doubled
    ("cam_0" -> "CAM_0", "front" -> "CAM_FRONT")."""
    rest = re.sub(r"^CAM_?", "", camera.upper())
    return f"CAM_{rest or camera.upper()}"


def channel_names(ds: Dataset, names: list[str], cameras: list[str] | None) -> dict[str, dict[str, str]]:
    """Per scenario, each exported camera's name -> its channel: every camera by its own name (``channel``), or
    the ``cameras`` named (at most six) as nuScenes' ``CAMERA_CHANNELS`` in that order (one-line errors)."""
    if cameras is not None and not all(cameras):
        raise UserError(f"--nuscenes-channels: camera names, comma-separated (1 to {len(CAMERA_CHANNELS)}), got "
                        f"{','.join(cameras)!r}")
    if cameras is not None and not 1 <= len(cameras) <= len(CAMERA_CHANNELS) or cameras and len(set(cameras)) < len(
            cameras):
        raise UserError(f"--nuscenes-channels: 1 to {len(CAMERA_CHANNELS)} different camera names, got {cameras}")
    out = {}
    for name in names:
        cams = [c.name for c in ds.scenario(name).cameras]
        if cameras is None:
            out[name] = {c: channel(c) for c in cams}
            if len(set(out[name].values())) < len(cams):
                raise UserError(f"{name}: cameras {cams} share a nuScenes channel name ({list(out[name].values())})")
            continue
        missing = [c for c in cameras if c not in cams]
        if missing:
            raise UserError(f"--nuscenes-channels: scenario {name} has no camera {missing[0]} (it has {cams})")
        out[name] = dict(zip(cameras, CAMERA_CHANNELS))
    return out


def export_nuscenes(ds: Dataset, out_dir: str | Path, scenarios: list[str] | None = None, thresholds=None,
                    variant: str | None = None, channels: list[str] | None = None, refined: bool = True) -> Path:
    """Write the nuScenes tables and files of ``scenarios`` (all) under ``out_dir``; returns ``out_dir``.
    ``thresholds`` are not applied: the devkit filters by range and points itself. ``channels``: only these
    cameras (at most six), as nuScenes' CAM_FRONT, CAM_FRONT_RIGHT, CAM_FRONT_LEFT, CAM_BACK, CAM_BACK_LEFT,
    CAM_BACK_RIGHT in that order (what mmdetection3d's converter reads); None: every camera by its own name.
    ``refined`` False: every road user in its class's own category (buses and trucks as cars: what our models name,
    for the devkit's evaluation over car and pedestrian)."""
    out = Path(out_dir)
    names = scenarios if scenarios is not None else ds.scenario_names()
    if not (ds.info.has("depth") and ds.info.has("instance")):
        raise UserError(f"{ds.root}: the nuScenes export's pseudo-LiDAR needs depth and instance maps (camera data "
                        "has none)")
    named = channel_names(ds, names, channels)
    check_images(ds, names, variant)
    scenes = scene_names(ds, names, variant)  # every scene's and file's name checked before the first is written
    tables: dict[str, dict] = {t: {} for t in TABLES}
    _static_tables(tables)
    sweeps: dict[tuple[str, int], dict[int, int]] = {}  # (scenario, frame) -> points per road user, once per frame
    for name in names:
        offset = global_offset(ds, name)
        scenes_of = [_scene(ds, (name, var, named[name], offset, refined), out, tables, sweeps)
                     for var in export_variants(ds, name, variant)]
        _map(ds, name, offset, [token(s, "log") for s in scenes_of], (out, tables))
    for table, rows in tables.items():
        atomic_write_text(below(out, VERSION, f"{table}.json"), json.dumps([rows[k] for k in sorted(rows)], indent=0))
    splits = {SPLIT_NAMES[split]: sorted(sc for sc, (scenario, _) in scenes.items()
                                         if scenario in set(ds.split(split)))
              for split in ("train", "val", "test")}  # the devkit reads custom splits from VERSION/splits.json
    atomic_write_text(below(out, VERSION, "splits.json"), json.dumps(splits, indent=1))
    return out


def scene_names(ds: Dataset, scenarios: list[str], variant: str | None) -> dict[str, tuple[str, str]]:
    """Every scene an export of ``scenarios`` makes (``SCENARIO__VARIANT``) -> (scenario, variant), and the sweep
    files (``SCENARIO__fFRAME``), each checked for collisions and for length as a file name (``JoinedNames``)."""
    joined = JoinedNames("nuScenes scene", suffix="__f0000.png")
    sweeps = JoinedNames("nuScenes sweep file", suffix=".pcd.bin")
    out = {}
    for scenario in scenarios:
        for var in export_variants(ds, scenario, variant):
            name = joined(scenario, var)  # scene_name(scenario, var): what its tokens are made from
            out[name] = (scenario, var)
        for frame in ds.frames(scenario):
            sweeps(scenario, f"f{frame:04d}")
    return out


def _static_tables(tables: dict) -> None:
    """Categories, attributes and visibility bins, the same in every export."""
    categories = sorted({"vehicle.car", "vehicle.bus.rigid", "vehicle.truck", "human.pedestrian.adult"})
    for k, name in enumerate(categories):
        tables["category"][token("category", name)] = {"token": token("category", name), "name": name,
                                                       "description": name, "index": k}
    for name in ATTRIBUTES:
        tables["attribute"][token("attribute", name)] = {"token": token("attribute", name), "name": name,
                                                         "description": name}
    for tok, level, lo in VISIBILITY:
        tables["visibility"][tok] = {"token": tok, "level": level,
                                     "description": f"visible share of its most visible view from {lo:.0%}"}


def _sensor(tables: dict, name: str, modality: str) -> str:
    tok = token("sensor", name)
    tables["sensor"][tok] = {"token": tok, "channel": name, "modality": modality}
    return tok


def _map(ds: Dataset, scenario: str, offset: np.ndarray, logs: list[str], into: tuple[Path, dict]) -> None:
    """The scenario's map (``nuscenes_map.ground_map``) as ``maps/SCENARIO.png`` and its record, which its
    scenes' ``logs`` point to (the devkit links each log to its map)."""
    out, tables = into
    filename = f"maps/{scenario}.png"
    _, png = cv2.imencode(".png", ground_map(ds, scenario, offset))
    atomic_write_bytes(below(out, *filename.split("/")), png.tobytes())
    tables["map"][token("map", scenario)] = {"token": token("map", scenario), "log_tokens": sorted(logs),
                                             "category": "semantic_prior", "filename": filename}


def _scene(ds: Dataset, what: tuple, out: Path, tables: dict, sweeps: dict) -> str:
    """One scene, ``what`` = (scenario, lighting variant, its exported cameras' channels, the world -> global
    offset, whether categories are refined): its log, samples, sample data (cameras and the sweep), annotations and instances; ``sweeps``: the
    frames' sweeps written so far (a frame's is written once, for the first of its lighting variants). Returns
    the scene's name."""
    scenario, variant, named, offset, refined = what
    scene = scene_name(scenario, variant)
    scn0, frames = ds.scenario(scenario), ds.frames(scenario)
    log = token(scene, "log")
    tables["log"][log] = {"token": log, "logfile": scene, "vehicle": "rig", "date_captured": "2026-01-01",
                          "location": scenario.split("-s")[0]}
    users = {a.id: (a, category_of(a.name, a.cls, refined)) for a in scn0.actors}
    users = {aid: (a, cat) for aid, (a, cat) in users.items() if cat is not None}
    calib = {named[c.name]: _calibration(tables, scene, (c, named[c.name]), _ego_pose_matrix(scn0, c))
             for c in scn0.cameras if c.name in named}
    calib[LIDAR] = _calibration(tables, scene, None, None)
    samples = [sample_token(scenario, variant, f) for f in frames]
    speeds = _speeds(ds, scenario, frames)
    for k, f in enumerate(frames):
        tables["sample"][samples[k]] = {"token": samples[k], "timestamp": timestamp_us(f, scn0.fps),
                                        "prev": samples[k - 1] if k else "", "next": samples[k + 1] if k + 1 < len(frames)
                                        else "", "scene_token": token(scene)}
        counts = _sample_data(ds, (scenario, variant, f, named, offset), out, tables, calib, set(users), sweeps)
        _annotations(ds, (scenario, variant, offset), (f, frames), tables, users, counts, speeds)
    tables["scene"][token(scene)] = {"token": token(scene), "log_token": log, "nbr_samples": len(frames),
                                     "first_sample_token": samples[0], "last_sample_token": samples[-1],
                                     "name": scene, "description": f"{scenario} under {variant}"}
    for aid, (_, cat) in users.items():
        inst = token(scene, "instance", aid)
        tables["instance"][inst] = {"token": inst, "category_token": token("category", cat),
                                    "nbr_annotations": len(frames),
                                    "first_annotation_token": token(scene, "annotation", aid, frames[0]),
                                    "last_annotation_token": token(scene, "annotation", aid, frames[-1])}
    return scene


def _ego_pose_matrix(scn, cam) -> np.ndarray:
    """(4, 4) world pose of the ego a camera belongs to at this frame: its car's box frame, or the world."""
    if cam is None or cam.mounted_on is None:
        return np.eye(4)
    box = scn.actor(cam.mounted_on).box
    return pose_of(box.center, box.yaw)


def _calibration(tables: dict, scene: str, sensor: tuple | None, ego: np.ndarray | None) -> str:
    """The sensor's pose in its ego (the camera at frame 0 in its car: a rigid mount), intrinsics for a camera;
    ``sensor``: (camera, its channel), None for the LiDAR."""
    cam, name = sensor if sensor is not None else (None, LIDAR)
    tok = token(scene, "calibrated_sensor", name)
    pose = np.eye(4) if cam is None else np.linalg.inv(ego) @ cam.camera_to_world
    tables["calibrated_sensor"][tok] = {
        "token": tok, "sensor_token": _sensor(tables, name, "camera" if cam is not None else "lidar"),
        "translation": pose[:3, 3].tolist(), "rotation": matrix_quaternion(pose[:3, :3]),
        "camera_intrinsic": [] if cam is None else np.asarray(cam.K, dtype=np.float64).tolist()}
    return tok


def _sample_data(ds: Dataset, at: tuple, out: Path, tables: dict, calib: dict,
                 users: set[int], sweeps: dict) -> dict[int, int]:
    """A frame's sample data (each exported camera's image, the sweep) with their ego poses in the global frame,
    ``at`` = (scenario, variant, frame, the cameras' channels, the world -> global offset); the sweep's points
    per road user."""
    scenario, variant, frame, named, offset = at
    scene, scn = scene_name(scenario, variant), ds.scenario_at(scenario, frame)
    frames = ds.frames(scenario)
    stamp, k = timestamp_us(frame, scn.fps), frames.index(frame)
    ref = _ego_pose_matrix(scn, scn.cameras[0] if scn.cameras else None)
    lidar = f"samples/{LIDAR}/{scenario}__f{frame:04d}.pcd.bin"
    if (scenario, frame) not in sweeps:  # depth and instances are the same under every lighting
        points, sweeps[scenario, frame] = sweep(ds, scenario, frame, np.linalg.inv(ref), users)
        atomic_write_bytes(below(out, *lidar.split("/")), points.tobytes())
    entries = [(named[c.name], _ego_pose_matrix(scn, c), f"samples/{named[c.name]}/{scene}__f{frame:04d}.png",
                c.width, c.height, "png") for c in scn.cameras if c.name in named]
    entries.append((LIDAR, ref, lidar, 0, 0, "pcd"))
    for ch, ego, filename, width, height, fmt in entries:
        tok = token(scene, "sample_data", ch, frame)
        tables["ego_pose"][tok] = {"token": tok, "timestamp": stamp, "rotation": matrix_quaternion(ego[:3, :3]),
                                   "translation": (ego[:3, 3] + offset).tolist()}
        tables["sample_data"][tok] = {
            "token": tok, "sample_token": sample_token(scenario, variant, frame), "ego_pose_token": tok,
            "calibrated_sensor_token": calib[ch], "timestamp": stamp, "fileformat": fmt, "is_key_frame": True,
            "height": height, "width": width, "filename": filename,
            "prev": token(scene, "sample_data", ch, frames[k - 1]) if k else "",
            "next": token(scene, "sample_data", ch, frames[k + 1]) if k + 1 < len(frames) else ""}
        if fmt == "png":
            camera = next(c for c in scn.cameras if named.get(c.name) == ch)
            copy_file(ds.layout.rgb(scenario, camera.name, variant, frame), below(out, *filename.split("/")))
    return sweeps[scenario, frame]


def _annotations(ds: Dataset, scene_of: tuple, at: tuple[int, list[int]], tables: dict, users: dict,
                 counts: dict[int, int], speeds: dict[int, list[float]]) -> None:
    """Every road user at frame ``at[0]`` (of the scene's frames ``at[1]``) of ``scene_of`` = (scenario, variant,
    the world -> global offset): its box in the global frame, visibility, attribute (from ``speeds``), sweep
    points, and its track's links."""
    scenario, variant, offset = scene_of
    frame, frames = at
    scene, scn = scene_name(scenario, variant), ds.scenario_at(scenario, frame)
    visible: dict[int, float] = {}
    for cam in scn.cameras:
        for o in ds.read_labels(scenario, cam.name, frame).objects:
            visible[o.instance_id] = max(visible.get(o.instance_id, 0.0), o.visible_fraction or 0.0)
    k = frames.index(frame)
    for aid, (_, cat) in users.items():
        box = scn.actor(aid).box
        length, width, height = (float(v) for v in box.size)
        tok = token(scene, "annotation", aid, frame)
        track = speeds.get(aid, [])
        attribute = attribute_of(scn.actor(aid).cls, track[k] if track else None, max(track, default=0) > MOVING_M_S)
        tables["sample_annotation"][tok] = {
            "token": tok, "sample_token": sample_token(scenario, variant, frame),
            "instance_token": token(scene, "instance", aid), "visibility_token": visibility_token(visible.get(aid, 0.0)),
            "attribute_tokens": [token("attribute", attribute)],
            "translation": [float(v) for v in np.asarray(box.center, dtype=np.float64) + offset],
            "size": [width, length, height], "rotation": yaw_quaternion(float(box.yaw)),
            "prev": token(scene, "annotation", aid, frames[k - 1]) if k else "",
            "next": token(scene, "annotation", aid, frames[k + 1]) if k + 1 < len(frames) else "",
            "num_lidar_pts": counts.get(aid, 0), "num_radar_pts": 0}


def _speeds(ds: Dataset, scenario: str, frames: list[int]) -> dict[int, list[float | None]]:
    """Each tracked road user's ground speed at each frame (m/s, from frames.json); empty for one frame."""
    if len(frames) < 2:
        return {}
    seq = ds.sequence(scenario)
    return {aid: [float(np.hypot(*seq.frames[f].actors[aid].velocity[:2])) for f in frames] for aid in seq.tracks}
