"""A pseudo-LiDAR sweep of one frame: every rig camera's exact depth map back-projected into the reference car's
frame, in nuScenes' ``.pcd.bin`` layout (float32 x, y, z, intensity, ring per point; the ring is the camera's
index, the intensity 0)::

    points, counts = sweep(ds, scenario, frame, world_to_ego, road_users)   # (N, 5) float32, {actor id: points}

Every pixel that shows a road user becomes a point (so a road user some camera sees has points, one no camera
sees has none: what ``num_lidar_pts`` counts and the devkit's filter keeps); the rest of the scene is thinned
to every ``STRIDE``-th pixel in each direction, to keep a sweep about 100 kB.
"""
from __future__ import annotations

import numpy as np

from dataset_spec import Dataset
from dataset_spec.camera import pixel_directions_camera

STRIDE = 4  # background pixels kept: every STRIDE-th column of every STRIDE-th row


def sweep(ds: Dataset, scenario: str, frame: int, world_to_ego: np.ndarray,
          road_users: set[int]) -> tuple[np.ndarray, dict[int, int]]:
    """(N, 5) float32 points in the ego frame and the number of points on each road user (absent: none)."""
    scn = ds.scenario_at(scenario, frame)
    parts, counts = [], {}
    for ring, cam in enumerate(scn.cameras):
        depth = ds.read_depth(scenario, cam.name, frame)
        ids = ds.read_instance(scenario, cam.name, frame).astype(np.int64)
        rows, cols = np.indices(depth.shape)
        user = np.isin(ids, list(road_users))
        keep = (depth > 0) & (user | ((rows % STRIDE == 0) & (cols % STRIDE == 0)))
        v, u = rows[keep], cols[keep]
        rays = pixel_directions_camera(cam.K, np.stack([u, v], axis=-1).astype(np.float64))  # z = 1: planar depth
        cam_pts = rays * depth[keep][:, None]
        world = cam_pts @ cam.camera_to_world[:3, :3].T + cam.camera_to_world[:3, 3]
        ego = world @ world_to_ego[:3, :3].T + world_to_ego[:3, 3]
        parts.append(np.column_stack([ego, np.zeros(len(ego)), np.full(len(ego), ring)]))
        for aid, n in zip(*np.unique(ids[keep & user], return_counts=True)):
            counts[int(aid)] = counts.get(int(aid), 0) + int(n)
    points = np.concatenate(parts) if parts else np.zeros((0, 5))
    return points.astype(np.float32), counts
