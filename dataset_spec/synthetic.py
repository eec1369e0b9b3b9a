"""A tiny dataset made in numpy: boxes on a ground plane, ray-cast into exact depth and ids.

For tests and examples that need a valid dataset without Blender. Geometry is exact:
depth is the planar depth of the first box or ground hit, instance ids come from the same
ray cast, and actor meshes are the boxes themselves.

Example::

    root = write_synthetic_dataset(tmp_path / "ds", width=64, height=48)
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .boxes import box_corners, yaw_rotation
from .camera import pixel_rays
from .dataset import Dataset
from .splits import make_splits
from .schema import Actor, Box3D, CameraInfo, DatasetInfo, LightingVariant, Scenario
from .sequence import ActorState, FrameState, Sequence

GROUND_ID = 1
# Triangles of a box over its 8 corners (documented corner order), outward facing.
BOX_FACES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                      [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """camera_to_world (OpenCV axes) for a camera at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return c2w


def simple_intrinsics(width: int, height: int, hfov_deg: float = 70.0) -> np.ndarray:
    f = (width / 2) / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])


def ray_box_distances(origins, dirs, center, size, yaw) -> np.ndarray:
    """Distance along each ray (N, 3) to an oriented box, inf where it misses."""
    R = yaw_rotation(yaw)
    o = (origins - center) @ R
    d = dirs @ R
    half = np.asarray(size) / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - o) / d
        t2 = (half - o) / d
    tmin = np.nanmax(np.minimum(t1, t2), axis=-1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
    hit = (tmax >= np.maximum(tmin, 0)) & np.isfinite(tmin)
    return np.where(hit, np.where(tmin > 0, tmin, tmax), np.inf)


def raycast(scenario: Scenario, camera: CameraInfo):
    """Exact (depth (H, W) float32, instance (H, W) uint16, normal-ish shade (H, W)) of a box scene."""
    h, w = camera.height, camera.width
    v, u = np.mgrid[0:h, 0:w]
    uv = np.stack([u, v], axis=-1).reshape(-1, 2).astype(np.float64)
    origins, dirs = pixel_rays(camera.K, camera.camera_to_world, uv)
    best_t = np.full(len(uv), np.inf)
    best_id = np.zeros(len(uv), dtype=np.int64)
    for actor in scenario.actors:
        if actor.id == GROUND_ID:
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where(dirs[:, 2] < -1e-9, -origins[:, 2] / dirs[:, 2], np.inf)
        else:
            t = ray_box_distances(origins, dirs, actor.box.center, actor.box.size, actor.box.yaw)
        closer = t < best_t
        best_t[closer], best_id[closer] = t[closer], actor.id
    z_axis = camera.camera_to_world[:3, 2]
    depth = np.where(np.isfinite(best_t), best_t * (dirs @ z_axis), 0.0)
    shade = np.clip(0.35 + 0.65 * np.abs(dirs[:, 2]), 0, 1)
    return (depth.reshape(h, w).astype(np.float32), best_id.reshape(h, w).astype(np.uint16),
            shade.reshape(h, w))


def toy_scenario(name: str = "toy_01", width: int = 64, height: int = 48, seed: int = 0) -> Scenario:
    """Three cars, two pedestrians, a wall and the ground; three cameras looking across them."""
    rng = np.random.default_rng(seed)
    actors = [Actor(GROUND_ID, "ground", "other", Box3D(np.array([0, 0, -0.05]), np.array([60.0, 60.0, 0.1]), 0.0))]
    specs = [("car_a", "car", (0, 0), (4.2, 1.8, 1.5)), ("car_b", "car", (5, 3), (4.5, 1.9, 1.6)),
             ("car_c", "car", (-4, 5), (3.9, 1.7, 1.4)), ("ped_a", "pedestrian", (2, -3), (0.5, 0.6, 1.75)),
             ("ped_b", "pedestrian", (-2, -2), (0.5, 0.5, 1.7)), ("wall", "other", (0, 8), (8.0, 0.4, 2.5))]
    for i, (nm, cls, (x, y), size) in enumerate(specs, start=2):
        jitter = rng.uniform(-0.3, 0.3, 2)
        center = np.array([x + jitter[0], y + jitter[1], size[2] / 2])
        actors.append(Actor(i, nm, cls, Box3D(center, np.array(size, dtype=np.float64), float(rng.uniform(-0.5, 0.5)))))
    K = simple_intrinsics(width, height)
    eyes = [(-14, -6, 1.4), (12, -9, 1.4), (3, 16, 1.4)]
    cameras = [CameraInfo(f"cam_{i}", width, height, K.copy(), look_at(e, (0.5, 1.5, 0.8)), near=0.1, far=200.0)
               for i, e in enumerate(eyes)]
    lighting = [LightingVariant("noon", "noon.exr", 1.0), LightingVariant("dusk", "dusk.exr", 0.4)]
    return Scenario(name, actors, cameras, lighting, extras={"generator": "dataset_spec.synthetic", "seed": seed})


# road users that move in a synthetic sequence (actor name -> velocity, m/s); the others stand
SYNTHETIC_VELOCITIES = {"car_a": (3.0, 0.5, 0.0), "ped_a": (0.0, 1.2, 0.0), "car_c": (-2.0, 0.0, 0.0)}


def synthetic_sequence(scn: Scenario, frames: int, fps: float) -> Sequence:
    """``scn``'s road users over ``frames`` frames: those of ``SYNTHETIC_VELOCITIES`` at constant velocity."""
    states = [FrameState(f, f / fps) for f in range(frames)]
    for a in scn.actors:
        if a.cls not in ("car", "pedestrian"):
            continue
        v = np.array(SYNTHETIC_VELOCITIES.get(a.name, (0.0, 0.0, 0.0)))
        for st in states:
            st.actors[a.id] = ActorState(a.box.center + v * st.time_s, a.box.yaw, v.copy())
    for st in states:
        st.cameras = {c.name: c.camera_to_world.copy() for c in scn.cameras}
    return Sequence(fps, states)


def write_synthetic_dataset(root: str | Path, n_scenarios: int = 1, width: int = 64, height: int = 48,
                            seed: int = 0, frames: int = 1, fps: float = 2.0,
                            names: dict[str, list[str]] | None = None) -> Path:
    """Write a complete, valid dataset of toy box scenarios to ``root`` and return it; ``frames`` > 1: each
    a sequence (``synthetic_sequence``); ``names``: scenario name -> its lighting variants' names, instead of
    ``toy_01`` ... with noon and dusk."""
    root = Path(root)
    ds = Dataset.create(root, DatasetInfo(name="synthetic"))
    chosen = names or {f"toy_{k + 1:02d}": [] for k in range(n_scenarios)}
    names = []
    for k, (name, variants) in enumerate(chosen.items()):
        scn = toy_scenario(name, width, height, seed + k)
        if variants:
            scn.lighting = [LightingVariant(v, f"{v}.exr", 1.0 - 0.5 * j / len(variants)) for j, v in enumerate(variants)]
        for actor in scn.actors:
            actor.mesh = ds.write_mesh(scn.name, actor.id, box_corners(actor.box.center, actor.box.size, actor.box.yaw),
                                       BOX_FACES)
        if frames > 1:
            scn.frames, scn.fps = frames, fps
            ds.write_sequence(scn.name, synthetic_sequence(scn, frames, fps))
        ds.write_scenario(scn)
        palette = np.random.default_rng(seed + 100 + k).uniform(40, 230, size=(max(a.id for a in scn.actors) + 1, 3))
        palette[0] = (150, 190, 235)  # sky
        for frame in range(frames):
            now = ds.scenario_at(scn.name, frame)
            for cam in now.cameras:
                depth, inst, shade = raycast(now, cam)
                ds.write_depth(scn.name, cam.name, depth, frame)
                ds.write_instance(scn.name, cam.name, inst, frame)
                for variant in scn.lighting:
                    rgb = palette[inst] * np.where(inst > 0, shade * variant.strength, 1.0)[..., None]
                    ds.write_rgb(scn.name, cam.name, variant.name, np.clip(rgb, 0, 255).astype(np.uint8), frame)
        names.append(scn.name)
    ds.set_splits(make_splits(names, seed=seed))
    return root
