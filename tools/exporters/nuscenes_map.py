"""The map a nuScenes export carries for the devkit to draw under its sweeps (``render_sample_data``'s default
underlay): the scene's ground seen from above, as the devkit's ``MapMask`` reads it::

    mask = ground_map(ds, scenario, offset)     # (H, W) uint8: 255 on the ground, 0 elsewhere; row 0 is the top

A PNG at ``MAP_RESOLUTION_M`` a pixel whose bottom-left corner is the scene's global (0, 0) (the export's global
frame: our world moved by ``global_offset``). Its foreground is every pixel of every camera's first frame that
shows the static scene within ``GROUND_M`` of the ground (road, sidewalks, markings, lawns: not the road users,
not the walls above), back-projected by its exact depth and closed over small gaps; the rest is background.
"""
from __future__ import annotations

import cv2
import numpy as np

from dataset_spec import Dataset
from dataset_spec.camera import pixel_directions_camera
from dataset_spec.cli_support import UserError
from dataset_spec.nuscenes_format import MAP_MARGIN_M, MAP_RESOLUTION_M, scene_extent

MAX_MAP_PIXELS = 10 ** 8  # 100 MB of map: a scene about 1 km across
GROUND_M = 0.3  # a static point this low is ground (a curb's sidewalk included)
CLOSE_PX = 9  # gaps between back-projected pixels closed up to this (0.9 m)


def ground_map(ds: Dataset, scenario: str, offset: np.ndarray) -> np.ndarray:
    """(H, W) uint8 map of ``scenario``'s ground in its global frame (``offset``: world -> global), sized by what the
    cameras see: from the global origin to ``MAP_MARGIN_M`` beyond the farthest camera (the devkit draws the map
    about the ego), at most ``MAX_MAP_PIXELS`` (one line beyond)."""
    frame = ds.frames(scenario)[0]
    scn = ds.scenario_at(scenario, frame)
    seen = np.array([np.asarray(c.camera_to_world)[:2, 3] for c in scn.cameras]).reshape(-1, 2)
    hi = seen.max(axis=0) if len(seen) else scene_extent(ds, scenario)[1]
    width, height = (int(np.ceil((hi[k] + offset[k] + MAP_MARGIN_M) / MAP_RESOLUTION_M)) for k in (0, 1))
    if width * height > MAX_MAP_PIXELS:
        raise UserError(f"{scenario}: its nuScenes map would be {width} x {height} pixels at {MAP_RESOLUTION_M} m, "
                        f"above {MAX_MAP_PIXELS}: its cameras and road users lie {max(width, height) * MAP_RESOLUTION_M:.0f}"
                        " m apart (a scene, not a city)")
    mask = np.zeros((height, width), np.uint8)
    users = [a.id for a in scn.actors if a.cls in ds.info.detectable_classes]
    for cam in scn.cameras:
        depth = ds.read_depth(scenario, cam.name, frame)
        ids = ds.read_instance(scenario, cam.name, frame).astype(np.int64)
        keep = (depth > 0) & (ids > 0) & ~np.isin(ids, users)
        v, u = np.nonzero(keep)
        rays = pixel_directions_camera(cam.K, np.stack([u, v], axis=-1).astype(np.float64))
        world = (rays * depth[keep][:, None]) @ cam.camera_to_world[:3, :3].T + cam.camera_to_world[:3, 3]
        low = world[world[:, 2] < GROUND_M] + offset
        px = np.floor(low[:, 0] / MAP_RESOLUTION_M).astype(np.int64)
        py = height - 1 - np.floor(low[:, 1] / MAP_RESOLUTION_M).astype(np.int64)  # the image's rows run down
        inside = (px >= 0) & (px < width) & (py >= 0) & (py < height)
        mask[py[inside], px[inside]] = 255
    return cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((CLOSE_PX, CLOSE_PX), np.uint8))
