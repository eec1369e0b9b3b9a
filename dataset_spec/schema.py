"""The dataset's records as dataclasses, with strict JSON (de)serialisation.

``from_dict`` functions raise ``SpecError(path, "field: problem")``, so a malformed JSON
file is reported with its path and the offending field rather than a KeyError traceback.
Matrices are numpy arrays in memory and nested lists on disk.
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .boxes import box_corners, corners_match_box
from .camera import mirror_camera, pixel_rays, project_points, scale_intrinsics, translate_intrinsics
from .errors import SpecError
from .layout import MAX_FRAMES
from .names import check_name, check_relative_path, excerpt

MAX_WORLD_M = 1000.0  # every camera and box centre lies within this of the world's origin (a scene, not a map)

SPEC_VERSION = "1.2"
# 1.1: dataset.json "absent", labels with unknown visibility; 1.2: sequences (frames.json, per-frame view files)
SUPPORTED_VERSIONS = ("1.0", "1.1", "1.2")
# the per-view maps a dataset may declare absent (real camera data has neither): section 3 of SPEC.md
VIEW_MAPS = ("depth", "instance")
SPLIT_NAMES = ("train", "val", "test")
KITTI_OCCLUSION_LEVELS = {0: "fully visible", 1: "partly occluded", 2: "largely occluded", 3: "unknown"}


class Fields:
    """Typed access to a JSON object with errors that name the file and field."""

    def __init__(self, obj: Any, path: Path | str | None, where: str = ""):
        if not isinstance(obj, dict):
            raise SpecError(path, f"{where or 'top level'}: expected an object, got {type(obj).__name__}")
        self.obj, self.path, self.where = obj, path, where

    def _name(self, key: str) -> str:
        return f"{self.where}.{key}" if self.where else key

    def err(self, key: str, msg: str) -> SpecError:
        return SpecError(self.path, f"{self._name(key)}: {msg}")

    def get(self, key: str, kind, default=..., allow_none: bool = False):
        if key not in self.obj:
            if default is ...:
                raise self.err(key, "missing")
            return default
        value = self.obj[key]
        if value is None and allow_none:
            return None
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if kind is int and isinstance(value, bool) or not isinstance(value, kind):
            raise self.err(key, f"expected {getattr(kind, '__name__', kind)}, got {type(value).__name__}")
        if kind is float and not math.isfinite(value):
            raise self.err(key, "must be finite")
        return value

    def name(self, key: str) -> str:
        """A name that becomes a folder or file name (``dataset_spec.names``): the rule checked here,
        before any path is built from it."""
        value = self.get(key, str)
        why = check_name(value)
        if why is not None:
            raise self.err(key, f"name {excerpt(value)} {why}")
        return value

    def array(self, key: str, shape: tuple[int, ...]) -> np.ndarray:
        value = self.get(key, list)
        try:
            arr = np.array(value, dtype=np.float64)
        except (ValueError, TypeError):
            raise self.err(key, "not a numeric array") from None
        if arr.shape != shape:
            raise self.err(key, f"expected shape {shape}, got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise self.err(key, "has non-finite values")
        return arr

    def position(self, key: str, shape: tuple[int, ...]) -> np.ndarray:
        """``array`` of world metres, every entry within ``MAX_WORLD_M`` of the origin (a pose's rotation part too)."""
        arr = self.array(key, shape)
        if np.abs(arr).max() > MAX_WORLD_M:
            raise self.err(key, f"world coordinates beyond {MAX_WORLD_M:g} m of the origin "
                                f"({np.abs(arr).max():.3g} m)")
        return arr

    def sub(self, key: str) -> "Fields":
        return Fields(self.get(key, dict), self.path, self._name(key))

    def items(self, key: str, default=...) -> list["Fields"]:
        return [Fields(o, self.path, f"{self._name(key)}[{i}]") for i, o in enumerate(self.get(key, list, default))]


def extras_of(f: Fields) -> dict:
    return dict(f.get("extras", dict, {}))


# ----------------------------------------------------------------------------- dataset root
@dataclass(frozen=True)
class ClassInfo:
    id: int
    name: str
    detectable: bool


DEFAULT_CLASSES = (ClassInfo(1, "car", True), ClassInfo(2, "pedestrian", True), ClassInfo(3, "other", False))


@dataclass
class DatasetInfo:
    name: str
    classes: list[ClassInfo] = field(default_factory=lambda: list(DEFAULT_CLASSES))
    splits: dict[str, list[str]] = field(default_factory=lambda: {s: [] for s in SPLIT_NAMES})
    spec_version: str = SPEC_VERSION
    extras: dict = field(default_factory=dict)
    absent: list[str] = field(default_factory=list)  # VIEW_MAPS this dataset has none of (imported camera data)

    def has(self, view_map: str) -> bool:
        """Whether the dataset's views have ``view_map`` ("depth" or "instance")."""
        return view_map not in self.absent

    def class_id(self, name: str) -> int:
        for c in self.classes:
            if c.name == name:
                return c.id
        raise KeyError(f"unknown class {name!r}; known: {[c.name for c in self.classes]}")

    def class_name(self, class_id: int) -> str:
        for c in self.classes:
            if c.id == class_id:
                return c.name
        raise KeyError(f"unknown class id {class_id}")

    @property
    def detectable_classes(self) -> list[str]:
        """Names of the classes a detector predicts, in class-id order (their index = detector class)."""
        return [c.name for c in sorted(self.classes, key=lambda c: c.id) if c.detectable]

    @property
    def all_split_scenarios(self) -> list[str]:
        return [s for name in SPLIT_NAMES for s in self.splits.get(name, [])]

    def to_dict(self) -> dict:
        return {
            "spec_version": self.spec_version,
            "name": self.name,
            "classes": [{"id": c.id, "name": c.name, "detectable": c.detectable} for c in self.classes],
            "splits": {k: list(v) for k, v in self.splits.items()},
            "absent": list(self.absent),
            "extras": self.extras,
        }

    @classmethod
    def from_dict(cls, obj: Any, path=None) -> "DatasetInfo":
        f = Fields(obj, path)
        version = f.get("spec_version", str)
        if version not in SUPPORTED_VERSIONS:
            raise f.err("spec_version", f"unsupported version {excerpt(version)} (this reader knows {SUPPORTED_VERSIONS})")
        classes = [ClassInfo(c.get("id", int), c.name("name"), c.get("detectable", bool)) for c in f.items("classes")]
        ids = [c.id for c in classes]
        names = [c.name for c in classes]
        if len(set(ids)) != len(ids) or len(set(names)) != len(names):
            raise f.err("classes", "class ids and names must be unique")
        if any(i <= 0 or i > 255 for i in ids):
            raise f.err("classes", "class ids must be in 1..255 (0 means 'nothing' in semantic maps)")
        sf = f.sub("splits")
        splits = {}
        for key in sf.obj:
            if key not in SPLIT_NAMES:
                raise sf.err(key, f"unknown split (allowed: {SPLIT_NAMES})")
            lst = sf.get(key, list)
            for entry in lst:
                why = check_name(entry)
                if why is not None:
                    raise sf.err(key, f"scenario name {excerpt(entry)} {why}")
            splits[key] = list(lst)
        absent = f.get("absent", list, [])
        if not all(isinstance(a, str) for a in absent) or not set(absent) <= set(VIEW_MAPS) or len(set(absent)) != len(absent):
            raise f.err("absent", f"must list distinct per-view maps among {list(VIEW_MAPS)}, got {excerpt(absent)}")
        return cls(name=f.get("name", str), classes=classes, splits=splits, spec_version=version, extras=extras_of(f),
                   absent=list(absent))


# ----------------------------------------------------------------------------- scenario
@dataclass
class Box3D:
    center: np.ndarray  # (3,) world metres, middle of the box
    size: np.ndarray  # (3,) length, width, height
    yaw: float  # radians about +Z

    @property
    def corners(self) -> np.ndarray:
        return box_corners(self.center, self.size, self.yaw)

    def to_dict(self) -> dict:
        return {"center": np.asarray(self.center, float).tolist(), "size": np.asarray(self.size, float).tolist(),
                "yaw": float(self.yaw), "corners": self.corners.tolist()}

    @classmethod
    def from_fields(cls, f: Fields) -> "Box3D":
        box = cls(f.position("center", (3,)), f.array("size", (3,)), f.get("yaw", float))
        if np.any(box.size <= 0):
            raise f.err("size", "must be positive")
        if not corners_match_box(f.array("corners", (8, 3)), box.center, box.size, box.yaw):
            raise f.err("corners", "do not match center/size/yaw")
        return box


@dataclass
class Actor:
    id: int  # instance id, 1..65535, the value in instance segmentation
    name: str
    cls: str  # class name, one of the dataset's classes
    box: Box3D
    mesh: str | None = None  # path relative to the scenario folder
    extras: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"id": self.id, "name": self.name, "class": self.cls, "box": self.box.to_dict(),
                "mesh": self.mesh, "extras": self.extras}

    @classmethod
    def from_fields(cls, f: Fields) -> "Actor":
        aid = f.get("id", int)
        if not 1 <= aid <= 65535:
            raise f.err("id", f"instance id {aid} outside 1..65535")
        mesh = f.get("mesh", str, None, allow_none=True)
        if mesh is not None and (why := check_relative_path(mesh)) is not None:
            raise f.err("mesh", f"{excerpt(mesh)}: {why} (a path below the scenario folder)")
        return cls(aid, f.name("name"), f.get("class", str), Box3D.from_fields(f.sub("box")), mesh, extras_of(f))


@dataclass
class CameraInfo:
    name: str
    width: int
    height: int
    K: np.ndarray  # (3, 3) pixels
    camera_to_world: np.ndarray  # (4, 4), OpenCV camera axes
    mounted_on: int | None = None  # actor id of the car carrying the camera
    near: float = 0.1
    far: float = 1000.0
    extras: dict = field(default_factory=dict)

    def resized(self, width: int, height: int) -> "CameraInfo":
        """The camera of this view's image resized to ``width`` x ``height`` (the pose unchanged)."""
        K = scale_intrinsics(self.K, width / self.width, height / self.height)
        return replace(self, width=width, height=height, K=K,
                       camera_to_world=np.asarray(self.camera_to_world, dtype=np.float64))

    def mirrored(self) -> "CameraInfo":
        """The camera that sees the world mirrored in x = 0 as this image flipped left-right (``mirror_camera``)."""
        K, c2w = mirror_camera(self.K, self.camera_to_world, self.width)
        return replace(self, K=K, camera_to_world=c2w)

    def shifted(self, dx: float, dy: float) -> "CameraInfo":
        """The camera of this image with its content moved by (dx, dy) pixels (``translate_intrinsics``)."""
        return replace(self, K=translate_intrinsics(self.K, dx, dy))

    def project(self, points_world: np.ndarray):
        """(N, 3) world points -> pixels (N, 2) and depths (N,) (``camera.project_points``)."""
        return project_points(self.K, self.camera_to_world, points_world)

    def pixel_rays(self, uv: np.ndarray):
        """Pixels (N, 2) -> world ray origins and unit directions (``camera.pixel_rays``)."""
        return pixel_rays(self.K, self.camera_to_world, uv)

    def to_dict(self) -> dict:
        return {"name": self.name, "mounted_on": self.mounted_on, "width": self.width, "height": self.height,
                "K": np.asarray(self.K, float).tolist(), "camera_to_world": np.asarray(self.camera_to_world, float).tolist(),
                "near": self.near, "far": self.far, "extras": self.extras}

    @classmethod
    def from_fields(cls, f: Fields) -> "CameraInfo":
        w, h = f.get("width", int), f.get("height", int)
        if w <= 0 or h <= 0:
            raise f.err("width", f"resolution must be positive, got {w}x{h}")
        return cls(f.name("name"), w, h, f.array("K", (3, 3)), f.position("camera_to_world", (4, 4)),
                   f.get("mounted_on", int, None, allow_none=True), f.get("near", float, 0.1),
                   f.get("far", float, 1000.0), extras_of(f))


@dataclass
class LightingVariant:
    name: str
    hdr: str  # HDR file name (a built-in variant's generated file, or the user's)
    strength: float = 1.0
    rotation_deg: float = 0.0
    extras: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"name": self.name, "hdr": self.hdr, "strength": self.strength,
                "rotation_deg": self.rotation_deg, "extras": self.extras}

    @classmethod
    def from_fields(cls, f: Fields) -> "LightingVariant":
        return cls(f.name("name"), f.get("hdr", str), f.get("strength", float, 1.0),
                   f.get("rotation_deg", float, 0.0), extras_of(f))


@dataclass
class Scenario:
    name: str
    actors: list[Actor]
    cameras: list[CameraInfo]
    lighting: list[LightingVariant]
    extras: dict = field(default_factory=dict)  # generator, seed, occlusion statistics...
    frames: int = 1  # frames of the sequence (1.2; 1: one instant); poses after frame 0 in frames.json
    fps: float | None = None  # frames per second of a sequence

    def at(self, state) -> "Scenario":
        """This scenario at one frame: the road users' boxes and the cameras' poses of ``state`` (a
        ``dataset_spec.sequence.FrameState``), everything else as in frame 0."""
        actors = [replace(a, box=Box3D(np.asarray(state.actors[a.id].center, float), a.box.size,
                                       float(state.actors[a.id].yaw))) if a.id in state.actors else a
                  for a in self.actors]
        cameras = [replace(c, camera_to_world=np.asarray(state.cameras[c.name], float)) if c.name in state.cameras
                   else c for c in self.cameras]
        return replace(self, actors=actors, cameras=cameras)

    def actor(self, actor_id: int) -> Actor:
        for a in self.actors:
            if a.id == actor_id:
                return a
        raise KeyError(f"scenario {self.name}: no actor with id {actor_id}")

    def camera(self, name: str) -> CameraInfo:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(f"scenario {self.name}: no camera {name!r}; cameras: {[c.name for c in self.cameras]}")

    def class_of_instance(self, info: DatasetInfo) -> dict[int, int]:
        return {a.id: info.class_id(a.cls) for a in self.actors}

    def to_dict(self) -> dict:
        out = {"spec_version": SPEC_VERSION, "name": self.name,
               "actors": [a.to_dict() for a in self.actors], "cameras": [c.to_dict() for c in self.cameras],
               "lighting": [v.to_dict() for v in self.lighting], "extras": self.extras}
        if self.frames > 1:
            out["sequence"] = {"frames": self.frames, "fps": self.fps}
        return out

    @classmethod
    def from_dict(cls, obj: Any, path=None) -> "Scenario":
        f = Fields(obj, path)
        version = f.get("spec_version", str)
        if version not in SUPPORTED_VERSIONS:
            raise f.err("spec_version", f"unsupported version {excerpt(version)}")
        frames, fps = 1, None
        if "sequence" in f.obj:
            seq = f.sub("sequence")
            frames, fps = seq.get("frames", int), seq.get("fps", float)
            if not (1 <= frames <= MAX_FRAMES and 0 < fps < math.inf):  # before anything is built from them
                raise seq.err("frames", f"frames 1..{MAX_FRAMES} and a finite fps > 0, got {excerpt(frames)} and "
                                        f"{excerpt(fps)}")
        scn = cls(f.name("name"), [Actor.from_fields(a) for a in f.items("actors")],
                  [CameraInfo.from_fields(c) for c in f.items("cameras")],
                  [LightingVariant.from_fields(v) for v in f.items("lighting")], extras_of(f), frames, fps)
        for kind, names in (("actor id", [a.id for a in scn.actors]), ("camera name", [c.name for c in scn.cameras]),
                            ("lighting name", [v.name for v in scn.lighting])):
            dup = sorted(n for n, count in Counter(names).items() if count > 1)  # linear in the actors
            if dup:
                raise SpecError(path, f"duplicate {kind}(s): {dup}")
        ids = {a.id for a in scn.actors}  # a reference between records is checked where the file is read
        lost = next((c for c in scn.cameras if c.mounted_on is not None and c.mounted_on not in ids), None)
        if lost is not None:
            raise SpecError(path, f"camera {lost.name}: mounted_on {lost.mounted_on} is not an actor id")
        return scn
