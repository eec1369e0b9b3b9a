"""The scenario catalog: procedural scenes, deterministic per (name, seed). No bpy.

``toy`` is a tiny scene for tests. ``intersection_01`` ... ``intersection_12`` are urban
junctions (see ``blender_tools.intersections``) built for occlusion: parked vans, buses and
building corners hide pedestrians and cars from some car cameras while cameras on the crossing
roads see them.

Example::

    model = build_model("intersection_07", seed=0)     # SceneModel
    for name, description in list_scenarios(): ...
"""
from __future__ import annotations

import math

import numpy as np

from . import assets
from .scene_model import ActorModel, CameraRig, Part, SceneModel


def toy(seed: int = 0) -> SceneModel:
    """Ground, a wall, a parked van, 3 cars (2 with cameras), 2 pedestrians (one behind the van)."""
    rng = np.random.default_rng(seed)
    actors = [
        ActorModel(1, "ground", "other", [Part("box", (40, 40, 0.1), (0, 0, -0.05), color=(0.3, 0.3, 0.3),
                                               material="asphalt")]),
        ActorModel(2, "wall", "other", assets.wall_parts(rng, 6.0, 2.0), location=(0, 7, 0)),
        ActorModel(3, "van", "car", assets.van_parts(rng), location=(1.0, -1.0, 0), yaw=0.0),
        ActorModel(4, "car_cam_a", "car", assets.car_parts(rng), location=(-12.0, -1.2, 0), yaw=0.0),
        ActorModel(5, "car_cam_b", "car", assets.car_parts(rng), location=(3.0, -13.0, 0), yaw=math.pi / 2),
        ActorModel(6, "car_parked", "car", assets.car_parts(rng), location=(-2.0, 3.5, 0), yaw=0.3),
        ActorModel(7, "ped_hidden", "pedestrian", assets.pedestrian_parts(rng), location=(1.0, 0.6, 0),
                   yaw=math.pi / 2),
        ActorModel(8, "ped_open", "pedestrian", assets.pedestrian_parts(rng), location=(-4.0, -2.5, 0), yaw=0.5),
    ]
    cameras = [CameraRig("cam_a", "car_cam_a", offset=(0.4, 0.35, 1.4)),
               CameraRig("cam_b", "car_cam_b", offset=(0.4, 0.35, 1.4), lens_mm=20.0)]
    return SceneModel("toy", seed, actors, cameras, extras={"layout": "toy"})


def _intersections():
    from .intersections import LAYOUTS, build_intersection

    return {name: (desc, (lambda seed, n=name: build_intersection(n, seed))) for name, desc in LAYOUTS.items()}


def catalog() -> dict:
    """{name: (description, builder(seed) -> SceneModel)}."""
    out = {"toy": ("tiny test scene: 3 cars (2 cameras), van, wall, 2 pedestrians", toy)}
    out.update(_intersections())
    return out


def list_scenarios() -> list[tuple[str, str]]:
    return [(name, desc) for name, (desc, _) in catalog().items()]


def build_model(name: str, seed: int = 0) -> SceneModel:
    cat = catalog()
    if name not in cat:
        raise KeyError(f"unknown scenario {name!r} (known: {', '.join(cat)})")
    model = cat[name][1](seed)
    model.name = name
    model.check()
    return model
