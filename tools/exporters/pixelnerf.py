"""The original pixelNeRF-YOLO layout, so that code can consume our data.

::

    OUT/train.lst, val.lst, test.lst        scene folder names, one a line
    OUT/<scene>/image_XXXX.png              view XXXX (camera index in the scenario)
    OUT/<scene>/extrinsic_XXXX.npy          4x4 world-to-camera, *Blender* camera axes (x right, y up, -z forward)
    OUT/<scene>/intrinsic_0000.npy          3x3 K shared by the views (of view 0; if the cameras'
                                            K differ, intrinsic_XXXX.npy is written for every view too)
    OUT/<scene>/projected_bboxes_XXXX.txt   YOLO ``cls cx cy w h`` normalised; 0 = human, 1 = car

A scene is a scenario at one frame (``<scenario>__f<frame>`` for a sequence, ``__<variant>`` added with
``variant='all'``). Classes other than
pedestrian and car are left out (the original code knows only these two).

Usage::

    folder = export_pixelnerf(ds, "out/exports/pixelnerf")
    scene = read_pixelnerf_scene(folder / "toy_01")
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from dataset_spec import Dataset, LabelThresholds
from dataset_spec.atomic import atomic_path, atomic_write_text
from dataset_spec.boxes import box_to_yolo
from dataset_spec.camera import invert_rigid, opencv_to_blender_camera_to_world
from dataset_spec.names import JoinedNames, below

from .common import copy_file, export_views

PIXELNERF_CLASSES = {"pedestrian": 0, "car": 1}  # the original code's 0 = human, 1 = car
SPLITS = ("train", "val", "test")


def blender_world_to_camera(camera_to_world: np.ndarray) -> np.ndarray:
    """4x4 world-to-camera in Blender camera axes from the spec's OpenCV camera_to_world."""
    return invert_rigid(opencv_to_blender_camera_to_world(camera_to_world))


def _save_npy(path: Path, array: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        np.save(tmp, np.asarray(array, dtype=np.float64))


def export_pixelnerf(ds: Dataset, out_dir: str | Path, scenarios: list[str] | None = None,
                     thresholds: LabelThresholds | None = None, variant: str | None = None) -> Path:
    """Write one folder per scene plus the split lists under ``out_dir``; returns ``out_dir``."""
    out = Path(out_dir)
    lists: dict[str, set[str]] = {s: set() for s in SPLITS}
    views_by_scene: dict[str, list] = {}
    joined = JoinedNames("pixelNeRF scene folder")  # a scene: one frame of a scenario (under one variant)
    for view in export_views(ds, scenarios, thresholds, variant):
        scene = joined(view.scenario, *([f"f{view.frame:04d}"] if ds.scenario(view.scenario).frames > 1 else []),
                       *([view.variant] if variant == "all" else []))
        views_by_scene.setdefault(scene, []).append(view)
        if view.split in lists:
            lists[view.split].add(scene)
    for scene, views in views_by_scene.items():
        folder = below(out, scene)
        same_K = all(np.allclose(v.camera.K, views[0].camera.K) for v in views)
        _save_npy(folder / "intrinsic_0000.npy", views[0].camera.K)
        for v in views:
            n = f"{v.camera_index:04d}"
            copy_file(v.image_path, folder / f"image_{n}.png")
            _save_npy(folder / f"extrinsic_{n}.npy", blender_world_to_camera(v.camera.camera_to_world))
            if not same_K:
                _save_npy(folder / f"intrinsic_{n}.npy", v.camera.K)
            lines = []
            for o in v.labels:
                if o.cls in PIXELNERF_CLASSES:
                    cx, cy, w, h = np.clip(box_to_yolo(o.box, v.camera.width, v.camera.height), 0.0, 1.0)
                    lines.append(f"{PIXELNERF_CLASSES[o.cls]} {cx:.6f} {cy:.6f} {w:.6f} {h:.6f}\n")
            atomic_write_text(folder / f"projected_bboxes_{n}.txt", "".join(lines))
    for split, scenes in lists.items():
        atomic_write_text(out / f"{split}.lst", "".join(f"{s}\n" for s in sorted(scenes)))
    return out


def read_pixelnerf_scene(folder: str | Path) -> dict:
    """Read a scene folder -> ``{"views": [index...], "K": (3, 3), "extrinsics": {index: (4, 4)},
    "boxes": {index: (N, 5) array of cls cx cy w h}}``."""
    folder = Path(folder)
    views = sorted(int(p.stem.split("_")[1]) for p in folder.glob("image_*.png"))
    boxes = {}
    for i in views:
        text = (folder / f"projected_bboxes_{i:04d}.txt").read_text()
        boxes[i] = np.array([[float(x) for x in line.split()] for line in text.splitlines() if line.strip()],
                            dtype=np.float64).reshape(-1, 5)
    return {"views": views, "K": np.load(folder / "intrinsic_0000.npy"),
            "extrinsics": {i: np.load(folder / f"extrinsic_{i:04d}.npy") for i in views}, "boxes": boxes}
