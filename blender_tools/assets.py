"""Low-poly procedural assets as lists of ``Part`` (no bpy): cars, vans, buses, trucks,
pedestrians, buildings, trees, poles, walls.

Every builder takes a ``numpy.random.Generator`` and returns parts in the actor's local frame
(x forward, y left, z up, origin on the ground under the centre), so sizes and colours vary
but a given seed always gives the same asset.
"""
from __future__ import annotations

import math

import numpy as np

from .scene_model import Part

CAR_COLORS = [(0.55, 0.02, 0.02), (0.02, 0.05, 0.35), (0.8, 0.8, 0.8), (0.03, 0.03, 0.03), (0.25, 0.25, 0.27),
              (0.6, 0.45, 0.05), (0.05, 0.25, 0.08), (0.5, 0.5, 0.55), (0.75, 0.3, 0.02), (0.15, 0.3, 0.5)]
SKIN = [(0.85, 0.65, 0.5), (0.6, 0.42, 0.3), (0.35, 0.22, 0.14), (0.95, 0.78, 0.65)]
CLOTH = [(0.1, 0.1, 0.12), (0.6, 0.05, 0.05), (0.1, 0.2, 0.5), (0.8, 0.75, 0.6), (0.2, 0.4, 0.2),
         (0.9, 0.9, 0.9), (0.5, 0.3, 0.15), (0.7, 0.6, 0.1), (0.35, 0.35, 0.4)]
FACADE = [(0.78, 0.72, 0.6), (0.65, 0.55, 0.45), (0.85, 0.85, 0.8), (0.55, 0.3, 0.22), (0.7, 0.7, 0.72),
          (0.8, 0.65, 0.45), (0.45, 0.5, 0.55), (0.9, 0.8, 0.7)]
GLASS = (0.04, 0.05, 0.06)
RUBBER = (0.02, 0.02, 0.02)


def _pick(rng, options):
    return options[int(rng.integers(len(options)))]


def _wheels(length, width, radius, n_axles=2, overhang=0.75) -> list[Part]:
    xs = np.linspace(length / 2 - overhang, -length / 2 + overhang, n_axles)
    parts = []
    for x in xs:
        for side in (1, -1):
            parts.append(Part("cylinder", (2 * radius, 2 * radius, 0.22), (float(x), side * (width / 2 - 0.1), radius),
                              (math.pi / 2, 0, 0), RUBBER, "rubber", group="wheels"))
    return parts


def car_parts(rng, color=None) -> list[Part]:
    """A passenger car: body, glass cabin with roof, four wheels, lights (about 4.2 x 1.8 x 1.5 m)."""
    L = float(rng.uniform(3.8, 4.8))
    W = float(rng.uniform(1.68, 1.9))
    H = float(rng.uniform(1.38, 1.6))
    color = color or _pick(rng, CAR_COLORS)
    r = 0.31
    body_h = 0.62
    cabin_l = L * float(rng.uniform(0.45, 0.55))
    cabin_x = -L * float(rng.uniform(0.02, 0.1))
    base = 0.28
    parts = [
        Part("box", (L, W, body_h), (0, 0, base + body_h / 2), color=color, material="paint"),
        Part("box", (cabin_l, W * 0.9, H - base - body_h - 0.05), (cabin_x, 0, (base + body_h + H - 0.05) / 2),
             color=GLASS, material="glass"),
        Part("box", (cabin_l * 0.92, W * 0.92, 0.06), (cabin_x, 0, H - 0.03), color=color, material="paint"),
    ]
    for side in (1, -1):
        parts.append(Part("box", (0.05, 0.3, 0.12), (L / 2, side * (W / 2 - 0.25), base + body_h - 0.15),
                          color=(1.0, 0.95, 0.8), material="light"))
        parts.append(Part("box", (0.05, 0.25, 0.1), (-L / 2, side * (W / 2 - 0.22), base + body_h - 0.12),
                          color=(0.7, 0.02, 0.02), material="light"))
    return parts + _wheels(L, W, r, 2, overhang=0.72)


def van_parts(rng, color=None) -> list[Part]:
    """A delivery van (about 5.3 x 2.0 x 2.4 m): tall box body, windscreen, four wheels."""
    L, W, H = float(rng.uniform(4.9, 6.0)), float(rng.uniform(1.95, 2.1)), float(rng.uniform(2.2, 2.6))
    color = color or _pick(rng, [(0.9, 0.9, 0.9), (0.85, 0.85, 0.8), (0.1, 0.2, 0.45), (0.7, 0.1, 0.05)])
    base = 0.3
    parts = [Part("box", (L, W, H - base), (0, 0, (H + base) / 2), color=color, material="paint"),
             Part("box", (0.06, W * 0.85, 0.7), (L / 2, 0, H - 0.65), color=GLASS, material="glass")]
    return parts + _wheels(L, W, 0.35, 2, overhang=0.85)


def bus_parts(rng, color=None) -> list[Part]:
    """A city bus (about 11.5 x 2.55 x 3.1 m) with a window band and six wheels."""
    L, W, H = float(rng.uniform(10.5, 12.5)), 2.55, float(rng.uniform(2.95, 3.3))
    color = color or _pick(rng, [(0.8, 0.65, 0.05), (0.1, 0.35, 0.6), (0.7, 0.05, 0.05), (0.9, 0.9, 0.9)])
    base = 0.35
    parts = [Part("box", (L, W, H - base), (0, 0, (H + base) / 2), color=color, material="paint"),
             Part("box", (L - 0.6, W + 0.02, 1.1), (0, 0, base + 1.55), color=GLASS, material="glass"),
             Part("box", (0.04, W * 0.9, 1.4), (L / 2, 0, base + 1.5), color=GLASS, material="glass")]
    return parts + _wheels(L, W, 0.48, 3, overhang=2.2)


def truck_parts(rng, color=None) -> list[Part]:
    """A box truck (about 8 x 2.5 x 3.5 m): cab and cargo box."""
    L, W, H = float(rng.uniform(7.0, 9.0)), 2.5, float(rng.uniform(3.2, 3.8))
    color = color or _pick(rng, CAR_COLORS)
    cab_l = 1.9
    base = 0.4
    parts = [Part("box", (cab_l, W, 2.6 - base), (L / 2 - cab_l / 2, 0, (2.6 + base) / 2), color=color, material="paint"),
             Part("box", (0.05, W * 0.85, 0.8), (L / 2, 0, 2.0), color=GLASS, material="glass"),
             Part("box", (L - cab_l - 0.1, W, H - base - 0.1), (-cab_l / 2 - 0.05, 0, (H + base + 0.1) / 2),
                  color=(0.88, 0.88, 0.86), material="paint")]
    return parts + _wheels(L, W, 0.5, 3, overhang=1.2)


def pedestrian_parts(rng, pose: str = "walk") -> list[Part]:
    """A person (1.5-1.95 m): legs, torso, arms, head; ``pose`` 'walk' spreads the legs."""
    h = float(rng.uniform(1.5, 1.95))
    skin, top, bottom = _pick(rng, SKIN), _pick(rng, CLOTH), _pick(rng, CLOTH)
    leg_h = 0.47 * h
    torso_h = 0.32 * h
    head = 0.13 * h
    stride = 0.35 if pose == "walk" else 0.0
    w = float(rng.uniform(0.34, 0.46))
    parts = []
    for side, swing in ((1, stride), (-1, -stride)):
        parts.append(Part("box", (0.15, 0.14, leg_h), (0, side * w * 0.25, leg_h / 2), (0, swing, 0),
                          bottom, "cloth"))
        parts.append(Part("box", (0.1, 0.09, torso_h * 1.05), (0, side * (w / 2 + 0.05), leg_h + torso_h * 0.45),
                          (0, -swing * 0.8, 0), top, "cloth"))
    parts.append(Part("box", (0.24, w, torso_h), (0, 0, leg_h + torso_h / 2), color=top, material="cloth"))
    parts.append(Part("sphere", (head * 0.85, head * 0.8, head), (0, 0, leg_h + torso_h + head * 0.55),
                      color=skin, material="skin"))
    return parts


def tree_parts(rng) -> list[Part]:
    h = float(rng.uniform(4.0, 7.5))
    crown = float(rng.uniform(2.2, 4.0))
    green = (float(rng.uniform(0.05, 0.15)), float(rng.uniform(0.2, 0.35)), float(rng.uniform(0.04, 0.1)))
    return [Part("cylinder", (0.3, 0.3, h * 0.6), (0, 0, h * 0.3), color=(0.25, 0.17, 0.1), material="bark"),
            Part("sphere", (crown, crown, crown * 1.1), (0, 0, h - crown * 0.45), color=green, material="foliage")]


def pole_parts(rng, kind: str = "light") -> list[Part]:
    h = float(rng.uniform(4.5, 7.0)) if kind == "light" else 2.6
    parts = [Part("cylinder", (0.14, 0.14, h), (0, 0, h / 2), color=(0.3, 0.32, 0.33), material="metal")]
    if kind == "light":
        # lamp arm top 1 cm below the pole's top cap (coincident top faces would render black)
        parts.append(Part("box", (1.2, 0.12, 0.1), (0.55, 0, h - 0.06), color=(0.3, 0.32, 0.33), material="metal"))
    else:  # traffic sign
        parts.append(Part("cylinder", (0.65, 0.65, 0.04), (0.03, 0, h - 0.3), (0, math.pi / 2, 0),
                          color=(0.8, 0.05, 0.05), material="paint"))
    return parts


def building_parts(rng, length: float, depth: float, height: float, style: str | None = None) -> list[Part]:
    """A building block with a window-grid facade (``facade``) or brick (``brick``) material."""
    style = style or ("brick" if rng.uniform() < 0.3 else "facade")
    color = _pick(rng, FACADE)
    parts = [Part("box", (length, depth, height), (0, 0, height / 2), color=color, material=style)]
    parts.append(Part("box", (length + 0.3, depth + 0.3, 0.3), (0, 0, height + 0.15), color=(0.3, 0.3, 0.3),
                      material="concrete"))
    if rng.uniform() < 0.5:  # shop-front awning on the street side (+y local)
        parts.append(Part("box", (length * 0.8, 1.2, 0.12), (0, depth / 2 + 0.6, 3.0),
                          color=_pick(rng, CLOTH), material="cloth"))
    return parts


def wall_parts(rng, length: float, height: float | None = None) -> list[Part]:
    height = height or float(rng.uniform(1.2, 2.4))
    color = _pick(rng, [(0.6, 0.58, 0.55), (0.55, 0.35, 0.25), (0.75, 0.73, 0.7)])
    return [Part("box", (length, 0.3, height), (0, 0, height / 2), color=color,
                 material="brick" if rng.uniform() < 0.5 else "concrete")]


VEHICLES = {"car": car_parts, "van": van_parts, "bus": bus_parts, "truck": truck_parts}
