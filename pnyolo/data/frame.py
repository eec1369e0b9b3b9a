"""One frame of camera images, no ground truth, as an ``Item`` (the inference API and the ONNX export)::

    item, scales = frame_item([rgb0, rgb1], [cam0, cam1], cfg.data, class_names)   # CameraInfo or (K, c2w)
"""
from __future__ import annotations

import cv2
import numpy as np
import torch

from dataset_spec.cli_support import UserError
from dataset_spec.labels2d import LabelThresholds
from dataset_spec.schema import CameraInfo
from pnyolo.data.grid import grid_for
from pnyolo.data.item import Item, ViewCamera


def camera_pose(camera) -> tuple[np.ndarray, np.ndarray]:
    """A camera's (K, camera_to_world) as float64 arrays, from a CameraInfo or a (K, camera_to_world) pair."""
    K, c2w = (camera.K, camera.camera_to_world) if hasattr(camera, "K") else camera
    return np.asarray(K, dtype=np.float64), np.asarray(c2w, dtype=np.float64)


def frame_item(images: list[np.ndarray], cameras: list, data_cfg, class_names: list[str]
               ) -> tuple[Item, list[tuple[float, float]]]:
    """images: (H, W, 3) uint8 RGB per view; cameras: CameraInfo or (K, camera_to_world) per view;
    ``data_cfg``: the checkpoint's ``data`` section (image scale, cell size). Returns the item (each
    view resized to the encoded size) and each view's resize factors."""
    if len(images) != len(cameras) or not images:
        raise UserError("give one camera per image (and at least one image)")
    h0, w0 = images[0].shape[:2]
    g = grid_for(w0, h0, data_cfg.image_scale, data_cfg.cell_px)
    imgs, Ks, c2ws, scales, views = [], [], [], [], []
    for img, cam in zip(images, cameras):
        h, w = img.shape[:2]
        K, c2w = camera_pose(cam)
        clip = {"near": cam.near, "far": cam.far} if hasattr(cam, "K") else {}  # CameraInfo's defaults otherwise
        view = CameraInfo("", w, h, np.asarray(K), np.asarray(c2w), **clip)
        imgs.append(torch.from_numpy(cv2.resize(img, (g.width, g.height), interpolation=cv2.INTER_AREA))
                    .permute(2, 0, 1).float() / 255)
        Ks.append(torch.tensor(view.resized(g.width, g.height).K, dtype=torch.float32))
        c2ws.append(torch.tensor(view.camera_to_world, dtype=torch.float32))
        scales.append((g.width / w, g.height / h))
        # a world box is put into the view as labels are: its clip range, the default label thresholds
        views.append(ViewCamera(view.near, view.far, (w, h), LabelThresholds()))
    item = Item(torch.stack(imgs), torch.stack(Ks), torch.stack(c2ws), g, views, class_names,
                list(range(len(images))), original_sizes=[v.size for v in views])
    return item, scales
