"""Intersections without end (no bpy): ``procedural-K`` (K >= 0) is a layout drawn from a distribution by K alone,
built like the hand-made ones (``blender_tools.intersections``), and ``procedural-K-sJ`` redraws its road users,
cameras and buildings (the layout stays, as for ``intersection_07-s2``).

What a draw chooses: 3-5 arms at angles at least 50 degrees apart (a T or Y as often as a cross), 1 or 2 lanes each
way per arm, a roundabout or not, parking or not, crosswalks or not, sidewalk width, building setback, heights and
brick share, trees and walls, the numbers of camera cars, moving and parked cars, pedestrians and of big vehicles
(vans, buses, trucks) parked near the junction. The draw is recorded in the scenario's extras (``procedural``).

Every scene is legal or drawn again (``legal``): the builder places nothing where something stands (buildings off
the roads and sidewalks, road users apart, camera cars on incoming lanes facing the junction); a build that places
fewer than three camera cars, or fewer than half the road users it asked for, is redrawn with the next sub-seed.

    model = build_procedural("procedural-12", seed=0)      # SceneModel
    layout_of("procedural-12")                              # its Layout (the motion rules read its streets)
"""
from __future__ import annotations

import re
from dataclasses import asdict

import numpy as np

from .scene_model import SceneModel
from .street import Layout, Street

NAME = re.compile(r"procedural-(0|[1-9][0-9]{0,8})")
DISTRIBUTION_SEED = 7301  # the draws' own stream: procedural-K is the same layout on every machine
MIN_GAP_DEG = 50.0
MIN_CAMERAS = 3
REDRAWS = 20
ON_STREET_M = 0.3  # a road user's centre lies within the roads and sidewalks grown by this


def is_procedural(name: str) -> bool:
    return NAME.fullmatch(name) is not None


def _arms(rng, n: int) -> list[float]:
    """``n`` arm angles (deg, the first at 0) at least ``MIN_GAP_DEG`` apart: evenly spread and jittered, or, for
    three arms, a T (straight through and one side street) half of the time."""
    if n == 3 and rng.uniform() < 0.5:
        side = float(rng.uniform(60, 120))
        return [0.0, round(side, 1), 180.0]
    step = 360.0 / n
    slack = (step - MIN_GAP_DEG) / 2
    angles = [0.0] + [round(k * step + float(rng.uniform(-slack, slack)), 1) for k in range(1, n)]
    return angles


def draw_layout(k: int) -> Layout:
    """The layout ``procedural-K`` stands for (the module docstring's distribution), by ``k`` alone."""
    rng = np.random.default_rng([DISTRIBUTION_SEED, k])
    n = int(rng.choice([3, 4, 5], p=[0.35, 0.45, 0.2]))
    arms = _arms(rng, n)
    roundabout = float(rng.uniform(5.0, 8.0)) if n >= 4 and rng.uniform() < 0.15 else 0.0
    lanes = [1] * n if roundabout else [int(rng.choice([1, 2], p=[0.7, 0.3])) for _ in range(n)]
    low = float(rng.uniform(6.0, 12.0))
    big = [str(v) for v in rng.choice(["van", "bus", "truck"], size=int(rng.integers(1, 5)), p=[0.5, 0.25, 0.25])]
    return Layout(f"procedural draw {k}: {n} arms at {', '.join(f'{a:g}' for a in arms)} deg"
                  + (f", roundabout {roundabout:.1f} m" if roundabout else ""),
                  arms, lanes=lanes, parking=bool(rng.uniform() < 0.7), sidewalk=round(float(rng.uniform(1.8, 5.0)), 2),
                  setback=round(float(rng.uniform(0.0, 2.0)), 2), heights=(round(low, 1), round(low + float(
                      rng.uniform(6.0, 12.0)), 1)), cameras=int(rng.integers(3, 9)),
                  pedestrians=int(rng.integers(8, 25)), moving=int(rng.integers(2, 9)), parked=int(rng.integers(2, 11)),
                  big=big, roundabout=roundabout, trees=int(rng.integers(0, 9)), walls=int(rng.integers(0, 5)),
                  brick=round(float(rng.uniform(0.0, 0.8)), 2), crosswalks=bool(rng.uniform() < 0.85))


def layout_of(name: str) -> Layout:
    """The layout of ``procedural-K`` or of its redraw ``procedural-K-sJ``."""
    return draw_layout(int(NAME.match(name).group(1)))


def legal(model: SceneModel, layout: Layout) -> bool:
    """Whether a build is a scene to keep: at least ``MIN_CAMERAS`` camera cars, each on an incoming lane facing
    the junction, every road user on a road or a sidewalk, and at least half the pedestrians and moving cars the
    layout asked for (the builder places nothing where something stands, so nothing overlaps: the validator checks
    that the road users' boxes are apart)."""
    cars = {a.name: a for a in model.actors}
    if len(model.cameras) < MIN_CAMERAS:
        return False
    for rig in model.cameras:
        car = cars.get(model.actor(rig.mounted_on).name)
        if car is None or car.extras.get("drive") != "camera" or car.extras.get("arm") is None:
            return False
        heading = np.array([np.cos(car.yaw), np.sin(car.yaw)])
        if heading @ -np.asarray(car.location[:2]) <= 0:  # facing away from the junction
            return False
    street = Street(layout)
    for a in model.actors:  # every road user on a road or a sidewalk
        if a.cls in ("car", "pedestrian") and not street.in_roads(np.asarray([a.location[:2]], float), ON_STREET_M):
            return False
    peds = sum(a.cls == "pedestrian" for a in model.actors)
    moving = sum(a.extras.get("drive") in ("lane", "junction") for a in model.actors)
    return peds >= layout.pedestrians // 2 and moving >= layout.moving // 2


def build_procedural(name: str, seed: int = 0) -> SceneModel:
    """The scene ``procedural-K`` for ``seed`` (its build redrawn with the next sub-seed until ``legal``)."""
    from .intersections import build_layout

    k = int(NAME.fullmatch(name).group(1))
    layout = draw_layout(k)
    for attempt in range(REDRAWS):
        model = build_layout(name, layout, seed, key=[DISTRIBUTION_SEED, k, attempt])
        if legal(model, layout):
            model.extras["procedural"] = {**asdict(layout), "heights": list(layout.heights), "k": k,
                                          "redrawn": attempt}
            return model
    raise ValueError(f"{name}: no legal scene in {REDRAWS} draws of its road users (seed {seed})")
