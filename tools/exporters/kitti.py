"""KITTI object label files: ``<split>/image_2``, ``<split>/label_2``, ``<split>/calib``.

A label line is ``type truncated occluded alpha left top right bottom h w l x y z rotation_y``:

* ``truncated`` = 1 - in-frame fraction; ``occluded`` = our KITTI occlusion level (0-3).
* Labels the thresholds left out become ``DontCare`` lines (2D box only, the other fields KITTI's
  placeholders): regions where a detection is neither right nor wrong.
* 2D box: our clipped amodal box, pixel centres at integer coordinates, clipped to KITTI's image
  extent [0, W - 1] x [0, H - 1] (the devkit's boxes never reach -0.5).
* 3D: ``h w l`` from the box size (length, width, height); ``x y z`` = the box's *bottom centre*
  in KITTI's *rectified* camera frame, which here is the camera's levelled frame (x horizontal
  right, y straight down, z horizontal forward; the camera's own axes are OpenCV's, as KITTI's).
  KITTI tools rebuild a box upright in that frame, so for our cameras, pitched a few degrees, the
  levelling rotation is ``R0_rect`` and a box rebuilt the devkit's way (corners rotated by
  ``rotation_y`` about y, projected with ``P2``) projects onto the exported 2D box.
* ``rotation_y``: heading about the rectified frame's y, 0 when the object faces its +x.
  ``alpha = rotation_y - atan2(x, z)``, both wrapped to [-pi, pi].

``calib/<stem>.txt`` holds ``P0..P3`` (= K [R0_rect^T | 0]: rectified points to pixels),
``R0_rect`` (camera -> rectified) and ``Tr_velo_to_cam`` (world -> camera, so the spec's world plays
the role of the velodyne frame): ``P2 @ R0_rect @ Tr_velo_to_cam`` is the camera's projection K [R | t].
For a level camera ``R0_rect`` is the identity and ``P2`` = [K | 0]. (A tool that reads the focal
length off ``P2[0, 0]`` is off by the pitch's cosine.)

Usage::

    folder = export_kitti(ds, "out/exports/kitti")
    objects = read_kitti_labels(folder / "train/label_2/toy_01__cam_0.txt")
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from dataset_spec import Box3D, CameraInfo, Dataset, LabelThresholds
from dataset_spec.atomic import atomic_write_text
from dataset_spec.camera import points_to_camera, transform_points, world_to_camera
from dataset_spec.names import below

from .common import copy_file, export_views

KITTI_TYPES = {"car": "Car", "pedestrian": "Pedestrian", "cyclist": "Cyclist"}
DONT_CARE = "DontCare"
FIELDS = ("type", "truncated", "occluded", "alpha", "left", "top", "right", "bottom", "h", "w", "l", "x", "y", "z",
          "rotation_y")


def _wrap(angle: float) -> float:
    return float((angle + np.pi) % (2 * np.pi) - np.pi)


def level_axes(camera_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World (3,) vectors of the camera's horizontal right and horizontal forward axes."""
    right = np.array(camera_to_world[:3, 0], dtype=np.float64)
    right[2] = 0.0
    right /= np.linalg.norm(right)
    return right, np.cross([0.0, 0.0, 1.0], right)


def rectifying_rotation(camera_to_world: np.ndarray) -> np.ndarray:
    """``R0_rect``: (3, 3) rotation from the camera's axes into its levelled frame (x horizontal
    right, y world down, z horizontal forward)."""
    right, forward = level_axes(camera_to_world)
    world_from_rect = np.column_stack([right, [0.0, 0.0, -1.0], forward])
    return world_from_rect.T @ np.asarray(camera_to_world, dtype=np.float64)[:3, :3]


def rotation_y_from_yaw(camera_to_world: np.ndarray, yaw: float) -> float:
    """KITTI rotation_y of an object with world yaw ``yaw`` (radians about +Z)."""
    right, forward = level_axes(camera_to_world)
    heading = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    return _wrap(np.arctan2(-heading @ forward, heading @ right))


def yaw_from_rotation_y(camera_to_world: np.ndarray, rotation_y: float) -> float:
    """Inverse of ``rotation_y_from_yaw``."""
    right, forward = level_axes(camera_to_world)
    heading = np.cos(rotation_y) * right - np.sin(rotation_y) * forward
    return float(np.arctan2(heading[1], heading[0]))


def kitti_3d(camera: CameraInfo, box: Box3D) -> dict:
    """``h w l x y z rotation_y alpha`` of a world box seen by ``camera``."""
    length, width, height = (float(v) for v in box.size)
    bottom = np.asarray(box.center, dtype=np.float64) - [0.0, 0.0, height / 2]
    x, y, z = rectifying_rotation(camera.camera_to_world) @ points_to_camera(camera.camera_to_world, bottom)
    ry = rotation_y_from_yaw(camera.camera_to_world, box.yaw)
    return {"h": height, "w": width, "l": length, "x": float(x), "y": float(y), "z": float(z), "rotation_y": ry,
            "alpha": _wrap(ry - np.arctan2(x, z))}


def box_from_kitti(camera: CameraInfo, obj: dict) -> Box3D:
    """World ``Box3D`` from a parsed KITTI object (inverse of ``kitti_3d``)."""
    in_camera = rectifying_rotation(camera.camera_to_world).T @ np.array([obj["x"], obj["y"], obj["z"]])
    bottom = transform_points(camera.camera_to_world, in_camera)
    center = bottom + [0.0, 0.0, obj["h"] / 2]
    return Box3D(center, np.array([obj["l"], obj["w"], obj["h"]]), yaw_from_rotation_y(camera.camera_to_world,
                                                                                       obj["rotation_y"]))


def calib_text(camera: CameraInfo) -> str:
    r0 = rectifying_rotation(camera.camera_to_world)
    P = np.hstack([np.asarray(camera.K, dtype=np.float64) @ r0.T, np.zeros((3, 1))])
    fmt = lambda m: " ".join(f"{v:.12e}" for v in np.asarray(m).ravel())  # noqa: E731
    lines = [f"P{i}: {fmt(P)}" for i in range(4)]
    lines += [f"R0_rect: {fmt(r0)}", f"Tr_velo_to_cam: {fmt(world_to_camera(camera.camera_to_world)[:3])}",
              f"Tr_imu_to_velo: {fmt(np.eye(4)[:3])}"]
    return "\n".join(lines) + "\n"


def kitti_box(box, camera: CameraInfo) -> tuple[float, ...]:
    """A clipped box in KITTI's image extent, pixel centres 0 .. W - 1 (ours reaches the pixels' outer edges)."""
    hi = [camera.width - 1, camera.height - 1] * 2
    return tuple(float(min(max(v, 0.0), m)) for v, m in zip(box, hi))


def export_kitti(ds: Dataset, out_dir: str | Path, scenarios: list[str] | None = None,
                 thresholds: LabelThresholds | None = None, variant: str | None = None) -> Path:
    """Write KITTI images, labels and calibration per split under ``out_dir``; returns ``out_dir``."""
    out = Path(out_dir)
    detectable = set(ds.info.detectable_classes)
    for view in export_views(ds, scenarios, thresholds, variant):
        base = out / view.split
        copy_file(view.image_path, below(base, "image_2", f"{view.stem}.png"))
        scn = ds.scenario_at(view.scenario, view.frame)
        lines = []
        for o in view.labels:
            if o.cls not in detectable:
                continue
            k = kitti_3d(view.camera, scn.actor(o.instance_id).box)
            x0, y0, x1, y1 = kitti_box(o.box, view.camera)
            lines.append(f"{KITTI_TYPES.get(o.cls, o.cls.capitalize())} {1.0 - o.in_frame_fraction:.2f} "
                         f"{o.occlusion_level} {k['alpha']:.4f} {x0:.2f} {y0:.2f} {x1:.2f} {y1:.2f} "
                         f"{k['h']:.4f} {k['w']:.4f} {k['l']:.4f} {k['x']:.4f} {k['y']:.4f} {k['z']:.4f} "
                         f"{k['rotation_y']:.4f}")
        for o in view.ignored:
            x0, y0, x1, y1 = kitti_box(o.box, view.camera)
            lines.append(f"{DONT_CARE} -1 -1 -10 {x0:.2f} {y0:.2f} {x1:.2f} {y1:.2f} -1 -1 -1 -1000 -1000 -1000 -10")
        atomic_write_text(below(base, "label_2", f"{view.stem}.txt"), "".join(f"{x}\n" for x in lines))
        atomic_write_text(below(base, "calib", f"{view.stem}.txt"), calib_text(view.camera))
    return out


def read_kitti_labels(path: str | Path) -> list[dict]:
    """Parse a KITTI label file -> list of dicts keyed by ``FIELDS`` (numbers as float, occluded int)."""
    objects = []
    for line in Path(path).read_text().splitlines():
        parts = line.split()
        if not parts:
            continue
        if len(parts) != len(FIELDS):
            raise ValueError(f"{path}: expected {len(FIELDS)} columns, got {len(parts)}")
        obj = {"type": parts[0], **{k: float(v) for k, v in zip(FIELDS[1:], parts[1:])}}
        obj["occluded"] = int(obj["occluded"])
        objects.append(obj)
    return objects
