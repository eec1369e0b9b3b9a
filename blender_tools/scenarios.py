"""The scenario catalog: procedural scenes, deterministic per (name, seed). No bpy.

``toy`` is a tiny scene for tests. ``intersection_01`` ... ``intersection_12`` are urban
junctions (see ``blender_tools.intersections``) built for occlusion: parked vans, buses and
building corners hide pedestrians and cars from some car cameras while cameras on the crossing
roads see them.

``procedural-K`` (K >= 0) is an intersection drawn from a distribution by K (``blender_tools.procedural``):
scenes without end. Every catalog and procedural name also comes in redrawn variants: ``NAME-sK`` (K >= 1) is the same layout
(arms, lanes, building style) with every random choice -- road users, cameras, buildings --
drawn again with seed ``seed + K``. Variants of the training layouts add scenes to learn from
while the held-out layouts stay unseen.

Example::

    model = build_model("intersection_07", seed=0)     # SceneModel
    more = build_model("intersection_07-s2", seed=0)   # the same layout drawn with seed 2
    for name, description in list_scenarios(): ...
"""
from __future__ import annotations

import math
import re

import numpy as np

from . import assets
from .procedural import build_procedural, is_procedural
from .scene_model import ActorModel, CameraRig, Part, SceneModel


def toy(seed: int = 0) -> SceneModel:
    """Ground, a wall, a parked van, 3 cars (2 with cameras), 2 pedestrians (one behind the van)."""
    rng = np.random.default_rng(seed)
    actors = [
        ActorModel(1, "ground", "other", [Part("box", (40, 40, 0.1), (0, 0, -0.05), color=(0.3, 0.3, 0.3),
                                               material="asphalt")]),
        ActorModel(2, "wall", "other", assets.wall_parts(rng, 6.0, 2.0), location=(0, 7, 0)),
        ActorModel(3, "van", "car", assets.van_parts(rng), location=(1.0, -1.0, 0), yaw=0.0),
        ActorModel(4, "car_cam_a", "car", assets.car_parts(rng), location=(-12.0, -1.2, 0), yaw=0.0,
                   extras={"drive": "camera"}),
        ActorModel(5, "car_cam_b", "car", assets.car_parts(rng), location=(3.0, -13.0, 0), yaw=math.pi / 2,
                   extras={"drive": "camera"}),
        ActorModel(6, "car_parked", "car", assets.car_parts(rng), location=(-2.0, 3.5, 0), yaw=0.3),
        ActorModel(7, "ped_hidden", "pedestrian", assets.pedestrian_parts(rng), location=(1.0, 0.6, 0),
                   yaw=math.pi / 2),
        ActorModel(8, "ped_open", "pedestrian", assets.pedestrian_parts(rng), location=(-4.0, -2.5, 0), yaw=0.5,
                   extras={"walk": True}),
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


PROCEDURAL_TEXT = ("K >= 0: an intersection drawn from a distribution by K (3-5 arms, lanes, roundabout, "
                   "parking, crosswalks, buildings, road users; blender_tools.procedural)")


def list_scenarios() -> list[tuple[str, str]]:
    return [(name, desc) for name, (desc, _) in catalog().items()] + [("procedural-K", PROCEDURAL_TEXT)]


_VARIANT = re.compile(r"^(?P<base>.+)-s(?P<k>[1-9][0-9]{0,8})$")  # K as the procedural seeds are bounded


def split_variant(name: str) -> tuple[str, int]:
    """``("intersection_03", 2)`` for ``"intersection_03-s2"``; ``(name, 0)`` for a catalog name.
    Raises KeyError naming the catalog for anything else."""
    cat = catalog()
    if name in cat or is_procedural(name):
        return name, 0
    m = _VARIANT.match(name)
    if m and (m["base"] in cat or is_procedural(m["base"])):
        return m["base"], int(m["k"])
    raise KeyError(f"unknown scenario {name!r} (known: {', '.join(cat)}, procedural-K for K >= 0; each also as "
                   "NAME-sK for K >= 1)")


def build_model(name: str, seed: int = 0) -> SceneModel:
    """The scene ``name`` (a catalog name or its variant ``NAME-sK``) for the run's ``seed``."""
    base, offset = split_variant(name)
    model = build_procedural(base, seed + offset) if is_procedural(base) else catalog()[base][1](seed + offset)
    model.name = name
    model.seed = seed + offset
    model.check()
    return model
