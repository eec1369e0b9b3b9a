"""What a nuScenes export of this dataset is made of, shared by the exporter (``tools.exporters.nuscenes``) and
the readers and writers of nuScenes results (``pnyolo``): tokens, the scene of a scenario under a lighting
variant, categories, attributes, visibility bins, timestamps and quaternions::

    scene_name("intersection_07", "noon")            # "intersection_07__noon": one scene per (scenario, variant)
    sample_token("intersection_07", "noon", 3)       # the sample of frame 3 of that scene
    category_of("bus_049", "car")                     # "vehicle.bus.rigid": our class refined by the actor's kind
    detection_name("vehicle.bus.rigid")               # "bus": the devkit's detection class
    visibility_token(0.55)                            # "2": 40-60 % of the road user visible in the rig's best view
    yaw_quaternion(0.3)                               # (w, x, y, z) of a turn about +Z
    global_offset(ds, "intersection_07")              # (3,) metres from our world to the scene's nuScenes global frame

Facts: ../shared/reference/FACTS.md ("nuScenes and its devkit").
"""
from __future__ import annotations

import hashlib
import math

import numpy as np

VERSION = "v1.0-occluded"  # the tables' folder: NuScenes(version=VERSION, dataroot=EXPORT)
# our splits as the devkit's custom splits (EXPORT/VERSION/splits.json): not nuScenes' own names, which its
# evaluations map to nuScenes' hard-coded scene lists (DetectionEval(..., eval_set=SPLIT_NAMES["test"]))
SPLIT_NAMES = {"train": "occ_train", "val": "occ_val", "test": "occ_test"}
# nuScenes' six camera channels, in the order mmdetection3d's converter (and the camera detectors after it) reads them
CAMERA_CHANNELS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
LIDAR = "LIDAR_TOP"  # the devkit's evaluation reads each sample's ego position from this channel
EPOCH_US = 1_600_000_000_000_000  # timestamps are microseconds: frame 0 of every scene at this instant
# The devkit's map (MapMask): a PNG at 0.1 m a pixel whose bottom-left corner is global (0, 0); it draws the map
# about an ego cropped 40 m x sqrt(2) each way, so every camera and road user lies this far inside the map.
MAP_RESOLUTION_M = 0.1
MAP_MARGIN_M = 80.0

# our class, refined by the actor's kind (its name's prefix), -> nuScenes category
CATEGORIES = {"bus": "vehicle.bus.rigid", "truck": "vehicle.truck", "van": "vehicle.car", "car": "vehicle.car",
              "camcar": "vehicle.car"}
CLASS_CATEGORY = {"car": "vehicle.car", "pedestrian": "human.pedestrian.adult"}
DETECTION_NAMES = {"vehicle.car": "car", "vehicle.bus.rigid": "bus", "vehicle.truck": "truck",
                   "human.pedestrian.adult": "pedestrian"}
ATTRIBUTES = ("vehicle.moving", "vehicle.stopped", "vehicle.parked", "pedestrian.moving", "pedestrian.standing",
              "pedestrian.sitting_lying_down", "cycle.with_rider", "cycle.without_rider")
MOVING_M_S = 0.5  # a road user faster than this is moving
# the devkit's four visibility bins (token, level, lower bound of the visible share)
VISIBILITY = (("1", "v0-40", 0.0), ("2", "v40-60", 0.4), ("3", "v60-80", 0.6), ("4", "v80-100", 0.8))


def token(*parts) -> str:
    """A stable 32-hex-digit token for a record (the same parts, the same token, on every machine)."""
    return hashlib.sha1("/".join(str(p) for p in parts).encode()).hexdigest()[:32]


def scene_name(scenario: str, variant: str) -> str:
    return f"{scenario}__{variant}"


def sample_token(scenario: str, variant: str, frame: int) -> str:
    """The sample of a scenario's ``frame`` under lighting ``variant`` (what results files name)."""
    return token(scene_name(scenario, variant), "sample", frame)


def timestamp_us(frame: int, fps: float | None) -> int:
    return EPOCH_US + int(round(frame * 1e6 / (fps or 1.0)))


def category_of(actor_name: str, cls: str, refined: bool = True) -> str | None:
    """The nuScenes category of a road user (None for a class with none: not exported); ``refined`` False: our class's
    own category (a bus or a truck is a car, as our models name it)."""
    if cls == "car" and refined:
        return CATEGORIES.get(actor_name.split("_")[0], "vehicle.car")
    return CLASS_CATEGORY.get(cls)


def detection_name(category: str) -> str:
    return DETECTION_NAMES[category]


def dataset_class_of(name: str) -> str | None:
    """The dataset class a detection name of the export comes from ("bus", "truck", "car" -> "car"; "pedestrian"
    -> "pedestrian"), so results naming any class the export writes are scored as that class; None for a name the
    export never writes."""
    for cls, category in CLASS_CATEGORY.items():
        kinds = CATEGORIES.values() if cls == "car" else ()
        if name in {DETECTION_NAMES[c] for c in (category, *kinds)}:
            return cls
    return None


def attribute_of(cls: str, speed: float | None, ever_moves: bool) -> str:
    """From the motion: moving above ``MOVING_M_S``; else a vehicle stopped (it moves at another frame) or parked,
    a pedestrian standing. ``speed`` None (one frame): still."""
    moving = speed is not None and speed > MOVING_M_S
    if cls == "pedestrian":
        return "pedestrian.moving" if moving else "pedestrian.standing"
    return "vehicle.moving" if moving else "vehicle.stopped" if ever_moves else "vehicle.parked"


def visibility_token(visible: float) -> str:
    """The bin of a road user's visible share (our most visible view of it at that frame; 0 unseen)."""
    return next(t for t, _, lo in reversed(VISIBILITY) if visible >= lo)


def yaw_quaternion(yaw: float) -> list[float]:
    """(w, x, y, z) of a turn by ``yaw`` about +Z."""
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


def quaternion_yaw(q) -> float:
    """The turn about +Z of a (w, x, y, z) quaternion (its heading, as the devkit's ``quaternion_yaw``)."""
    w, x, y, z = (float(v) for v in q)
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def matrix_quaternion(R: np.ndarray) -> list[float]:
    """(w, x, y, z) of a 3x3 rotation matrix (Shepperd's method: stable for every rotation)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.trace(R)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = math.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k]) * 2
        q = [0.0] * 4
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q = np.asarray(q)
    return (q / np.linalg.norm(q) * (1 if q[0] >= 0 else -1)).tolist()


def pose_of(center, yaw: float) -> np.ndarray:
    """(4, 4) the frame of a box: origin at its centre, x forward, z up."""
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = np.asarray(center, dtype=np.float64)
    return T


def scene_extent(ds, scenario: str) -> tuple[np.ndarray, np.ndarray]:
    """(lowest, highest) world x, y of every camera and road user of ``scenario`` over its frames."""
    xy = []
    for frame in ds.frames(scenario):
        scn = ds.scenario_at(scenario, frame)
        xy += [np.asarray(c.camera_to_world)[:2, 3] for c in scn.cameras]
        xy += [np.asarray(a.box.center, dtype=np.float64)[:2] for a in scn.actors]
    xy = np.array(xy, dtype=np.float64).reshape(-1, 2) if xy else np.zeros((1, 2))
    return xy.min(axis=0), xy.max(axis=0)


def global_offset(ds, scenario: str) -> np.ndarray:
    """(3,) metres added to ``scenario``'s world coordinates to give its export's global frame: every camera and
    road user at least ``MAP_MARGIN_M`` from the map's origin (whole 10 m, z unchanged). The exporter writes
    global poses and boxes with it; results files are read and written with it (one frame per scenario)."""
    lo, _ = scene_extent(ds, scenario)
    shift = np.ceil((MAP_MARGIN_M - lo) / 10.0) * 10.0
    return np.array([shift[0], shift[1], 0.0])


class GlobalFrames:
    """``global_offset`` of each scenario of ``ds``, computed once."""

    def __init__(self, ds):
        self.ds, self._offsets = ds, {}

    def __call__(self, scenario: str) -> np.ndarray:
        if scenario not in self._offsets:
            self._offsets[scenario] = global_offset(self.ds, scenario)
        return self._offsets[scenario]
