"""Procedural urban intersections ``intersection_01`` ... ``intersection_12`` (no bpy).

A layout is a set of road arms (angles from the junction centre, half widths), sidewalks,
buildings lining the arms (set back, never on a road), lane markings and crosswalks, trees,
poles and walls. Road users: 3-8 camera cars approaching the junction in their lanes (right-hand
traffic, one forward camera each at 1.3-1.5 m), other moving cars, parked cars, vans, buses and
trucks at the kerb near the junction, and pedestrians on crosswalks, on sidewalks and -- designed
for occlusion -- right behind parked vans/buses or stepping out between parked vehicles, where the
cars on the same arm cannot see them but the cars on the crossing arms can. Building corners hide
the cross traffic from each approaching car.

Deterministic per (name, seed): every random choice comes from ``numpy.random.default_rng``
seeded with the layout number and the seed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from . import assets
from .scene_model import ActorModel, CameraRig, Part, SceneModel
from .street import (ARM_LENGTH, BUILDING_GAP, BUILDING_STAGGER, LAYOUTS, LAYOUTS_SPEC, MARK_INSET, PARKING,  # noqa: F401
                     ROAD_STEP, Layout, Street, obb, overlap)

class _Builder(Street):
    def __init__(self, name: str, layout: Layout, seed: int, key: list[int] | None = None):
        super().__init__(layout)
        self.name, self.seed = name, seed
        self.rng = np.random.default_rng([*(key or [int(name.split("_")[-1])]), seed])
        self.actors: list[ActorModel] = []
        self.rigs: list[CameraRig] = []
        self.occupied: list[np.ndarray] = []
        self.footprints: list[np.ndarray] = []
        self.next_id = 1

    # ---------------------------------------------------------------- arms
    # ---------------------------------------------------------------- actors
    def add(self, name, cls, parts, xy, yaw, z=0.0, **extras) -> ActorModel:
        a = ActorModel(self.next_id, name, cls, parts, (float(xy[0]), float(xy[1]), float(z)), float(yaw), extras)
        self.next_id += 1
        self.actors.append(a)
        return a

    def free(self, quad, margin_quads=()) -> bool:
        return not any(overlap(quad, q) for q in list(self.occupied) + list(margin_quads))

    def place(self, kind: str, cls: str, parts, xy, yaw, footprint, name=None, **extras):
        quad = obb(xy, footprint[0] + 0.6, footprint[1] + 0.4, yaw)
        if not self.free(quad):
            return None
        self.occupied.append(quad)
        return self.add(name or f"{kind}_{self.next_id:03d}", cls, parts, xy, yaw, kind=kind, **extras)

    # ---------------------------------------------------------------- static world
    def static(self):
        L, rng = self.L, self.rng
        self.add("ground", "other", [Part("box", (2.6 * ARM_LENGTH, 2.6 * ARM_LENGTH, 0.1), (0, 0, -0.05),
                                          color=(0.42, 0.41, 0.39), material="pavement")], (0, 0), 0)
        road, walk, marks = [], [], []
        asphalt = (0.08, 0.08, 0.085)
        for k in range(len(L.arms)):
            a, e, n = self.arm(k)
            hw = self.hw[k]
            # The arms overlap at the junction. Overlapping faces in one plane render black in Cycles
            # (every shadow/bounce ray leaving one face hits the other at distance 0), so each arm
            # sits ROAD_STEP lower than the previous one: one top face is exposed, the others are
            # hidden just below it.
            road.append(Part("box", (ARM_LENGTH, 2 * hw, 0.04), (*(e * ARM_LENGTH / 2), -ROAD_STEP * k),
                             (0, 0, math.radians(a)), asphalt, "asphalt"))
            for side in (1, -1):
                s0 = self.corner_start(k, side, hw + L.sidewalk)
                length = ARM_LENGTH - s0
                c = e * (s0 + length / 2) + n * side * (hw + L.sidewalk / 2)
                walk.append(Part("box", (length, L.sidewalk, 0.15), (*c, 0.075), (0, 0, math.radians(a)),
                                 (0.55, 0.54, 0.52), "concrete"))
            sc = self.junction_clear(k)
            # crosswalk stripes (across the arm) and the stop line
            for off in np.arange(-hw + 0.5, hw - 0.3, 1.0) if L.crosswalks else ():
                c = e * (sc + 1.6) + n * off
                marks.append(Part("box", (3.0, 0.5, 0.02), (*c, 0.025), (0, 0, math.radians(a)), (0.9, 0.9, 0.88),
                                  "marking"))
            # stop line across the incoming lanes, ending MARK_INSET short of the road's side (a
            # marking side flush with the road side would share its plane)
            stop = hw - (PARKING if L.parking else 0) - MARK_INSET
            c = e * (sc + 3.6) - n * stop / 2
            marks.append(Part("box", (0.4, stop, 0.02), (*c, 0.025), (0, 0, math.radians(a)), (0.9, 0.9, 0.88),
                              "marking"))
            for s in np.arange(sc + 5.0, ARM_LENGTH - 2, 6.0):  # dashed centre line
                c = e * (s + 1.5)
                marks.append(Part("box", (3.0, 0.15, 0.02), (*c, 0.025), (0, 0, math.radians(a)), (0.9, 0.9, 0.88),
                                  "marking"))
        disc_z = min(-0.005, -ROAD_STEP * len(L.arms))  # junction disc: top below every arm's top
        if L.roundabout:
            road.append(Part("cylinder", (2 * (L.roundabout + 6.5),) * 2 + (0.04,), (0, 0, disc_z), color=asphalt,
                             material="asphalt"))
        else:
            r = max(self.hw) * 1.5
            road.append(Part("cylinder", (2 * r, 2 * r, 0.04), (0, 0, disc_z), color=asphalt, material="asphalt"))
        self.add("road", "other", road, (0, 0), 0)
        self.add("sidewalks", "other", walk, (0, 0), 0)
        self.add("markings", "other", marks, (0, 0), 0)
        if L.roundabout:
            # grass from 5 cm up (inside the kerb ring): bottoms at z=0 would be coincident
            isl = [Part("cylinder", (2 * L.roundabout, 2 * L.roundabout, 0.25), (0, 0, 0.175), color=(0.12, 0.3, 0.08),
                        material="grass"),
                   Part("cylinder", (2 * L.roundabout + 0.4, 2 * L.roundabout + 0.4, 0.2), (0, 0, 0.1),
                        color=(0.6, 0.6, 0.58), material="concrete")]
            self.add("island", "other", isl, (0, 0), 0)
            for i in range(3):
                ang = rng.uniform(0, 2 * np.pi)
                rad = rng.uniform(0, L.roundabout * 0.6)
                self.add(f"island_tree_{i}", "other", assets.tree_parts(rng), (rad * math.cos(ang), rad * math.sin(ang)),
                         0, z=0.3)

    def place_buildings(self):
        L, rng = self.L, self.rng
        for k in range(len(L.arms)):
            a, e, n = self.arm(k)
            for side in (1, -1):
                lat0 = self.hw[k] + L.sidewalk + L.setback
                s = self.corner_start(k, side, lat0)
                while s < ARM_LENGTH - 6:
                    length = float(rng.uniform(9, 18))
                    depth = float(rng.uniform(9, 15))
                    height = float(rng.uniform(*L.heights))
                    # Fronts of neighbours differ by a few cm (golden-ratio sequence over the buildings
                    # placed so far, no random draw): the roof slabs overhang 0.15 m and overlap across
                    # the small gap, and coplanar overlapping slab fronts would render black.
                    lo, hi = BUILDING_STAGGER
                    stagger = lo + (hi - lo) * ((len(self.footprints) * 0.6180339887498949) % 1.0)
                    front = lat0 + stagger  # away from the street: never onto a sidewalk
                    c = e * (s + length / 2) + n * side * (front + depth / 2)
                    yaw = math.radians(a) + (math.pi if side > 0 else 0.0)
                    quad = obb(c, length, depth, yaw)
                    shrink = obb(c, length - 0.2, depth - 0.2, yaw)
                    clear = obb(c, length + BUILDING_GAP / 2, depth + BUILDING_GAP / 2, yaw)  # no shared walls
                    if not self.in_roads(shrink, L.setback - 0.05) and not any(overlap(clear, b) for b in self.footprints):
                        style = "brick" if rng.uniform() < L.brick else "facade"
                        self.add(f"building_{self.next_id:03d}", "other",
                                 assets.building_parts(rng, length, depth, height, style), c, yaw, kind="building")
                        self.footprints.append(quad)
                        s += length + float(rng.choice([BUILDING_GAP, BUILDING_GAP, 2.5, 5.0]))
                    else:
                        s += 2.0

    def furniture(self):
        L, rng = self.L, self.rng
        n_arms = len(L.arms)
        for i in range(L.trees):
            k, side = i % n_arms, (1 if (i // n_arms) % 2 == 0 else -1)
            a, e, n = self.arm(k)
            s = self.junction_clear(k) + float(rng.uniform(8, 30))
            xy = e * s + n * side * (self.hw[k] + L.sidewalk - 0.7)
            self.add(f"tree_{i}", "other", assets.tree_parts(rng), xy, 0, z=0.15, kind="tree")
        for k in range(n_arms):  # a street light and a sign at each corner
            a, e, n = self.arm(k)
            sc = self.junction_clear(k)
            xy = e * (sc + 0.5) + n * (-(self.hw[k] + 0.5))
            self.add(f"pole_{k}", "other", assets.pole_parts(rng, "light"), xy, math.radians(a) + math.pi / 2, z=0.15)
            xy = e * (sc + 0.3) + n * (self.hw[k] + 0.5)
            self.add(f"sign_{k}", "other", assets.pole_parts(rng, "sign"), xy, math.radians(a) + math.pi, z=0.15)
        for i in range(L.walls):
            k = int(rng.integers(n_arms))
            side = 1 if rng.uniform() < 0.5 else -1
            a, e, n = self.arm(k)
            s = self.junction_clear(k) + float(rng.uniform(4, 20))
            length = float(rng.uniform(5, 10))
            xy = e * (s + length / 2) + n * side * (self.hw[k] + L.sidewalk - 0.15)
            quad = obb(xy, length, 0.3, math.radians(a))
            # checked against buildings and everything placed so far, other walls included (two walls
            # on one line would share their faces), and kept out of the way of later placements
            if self.free(obb(xy, length + 0.2, 0.5, math.radians(a))) and \
                    not any(overlap(quad, b) for b in self.footprints):
                self.occupied.append(quad)
                self.add(f"wall_{i}", "other", assets.wall_parts(rng, length), xy, math.radians(a), z=0.15, kind="wall")

    # ---------------------------------------------------------------- road users
    def vehicle(self, kind, k, s, lat, heading_in: bool, name=None, color=None, **extras):
        a, e, n = self.arm(k)
        parts = assets.VEHICLES[kind](self.rng, color) if color else assets.VEHICLES[kind](self.rng)
        xs = [p.location[0] + p.size[0] / 2 for p in parts] + [p.location[0] - p.size[0] / 2 for p in parts]
        length = max(xs) - min(xs)
        width = max(p.size[1] for p in parts if p.shape == "box")
        yaw = math.radians(a) + (math.pi if heading_in else 0.0)
        return self.place(kind, "car", parts, e * s + n * lat, yaw, (length, width), name=name, **extras)

    def road_users(self):
        L, rng = self.L, self.rng
        n_arms = len(L.arms)
        # camera cars: approaching the junction, spread over the arms
        cams = 0
        tries = 0
        while cams < L.cameras and tries < 200:
            k = (cams + tries) % n_arms
            tries += 1
            lane = int(rng.integers(self.lanes[k]))
            s = self.junction_clear(k) + float(rng.uniform(5, 24)) + 6 * (cams // n_arms)
            car = self.vehicle("car", k, s, self.lane_lateral(k, lane, True), True, name=f"camcar_{cams}",
                               drive="camera", arm=k, lane=lane)
            if car is None:
                continue
            eye = float(rng.uniform(1.3, 1.5))
            self.rigs.append(CameraRig(f"cam_{cams}", car.name, offset=(0.25, 0.35, eye),
                                       pitch_deg=float(rng.uniform(-4, 0)), lens_mm=float(rng.choice([20.0, 24.0, 28.0]))))
            cams += 1
        # big vehicles parked at the kerb near the crosswalks, with pedestrians hidden behind them
        for i, kind in enumerate(L.big):
            for _ in range(20):
                k = int(rng.integers(n_arms))
                side = -1 if rng.uniform() < 0.7 else 1  # mostly on the incoming side
                kerb = self.hw[k] - (1.15 if kind != "bus" else 1.35)
                if not L.parking:
                    kerb = self.hw[k] - 1.1
                s = self.junction_clear(k) + float(rng.uniform(6, 14)) + (4 if kind == "bus" else 0)
                v = self.vehicle(kind, k, s, side * kerb, side < 0, extras_role="occluder")
                if v is None:
                    continue
                a, e, n = self.arm(k)
                # a pedestrian on the sidewalk behind it, one stepping out in front of it
                for j, (ds, dl) in enumerate(((float(rng.uniform(-2, 2)), 1.0 + float(rng.uniform(0, 0.8))),
                                              (-(v.extras.get("length", 6.0) / 2 + 3.5), -0.6))):
                    xy = e * (s + ds) + n * side * (self.hw[k] + dl)
                    self.pedestrian(xy, math.radians(a) + (math.pi / 2) * (-side), role="hidden_behind_vehicle", arm=k)
                break
        # parked cars along the kerbs
        for i in range(L.parked if L.parking else min(L.parked, 2)):
            for _ in range(20):
                k = int(rng.integers(n_arms))
                side = 1 if rng.uniform() < 0.5 else -1
                s = self.junction_clear(k) + float(rng.uniform(4, 35))
                if self.vehicle("car", k, s, side * (self.hw[k] - 1.1), side < 0) is not None:
                    break
        # other moving traffic (some inside the junction)
        for i in range(L.moving):
            for _ in range(20):
                k = int(rng.integers(n_arms))
                incoming = rng.uniform() < 0.5
                if i % 3 == 2 and not L.roundabout:  # crossing the junction
                    a, e, n = self.arm(k)
                    s = float(rng.uniform(-4, 4))
                    kind = "car"
                    v = self.vehicle(kind, k, s, self.lane_lateral(k, 0, True), True, drive="junction", arm=k)
                else:
                    s = self.junction_clear(k) + float(rng.uniform(3, 35))
                    kind = "van" if rng.uniform() < 0.15 else "car"
                    lane = int(rng.integers(self.lanes[k]))
                    v = self.vehicle(kind, k, s, self.lane_lateral(k, lane, incoming), incoming, drive="lane", arm=k,
                                     lane=lane, incoming=bool(incoming))
                if v is not None:
                    break
        # pedestrians on crosswalks and sidewalks
        n_cross = L.pedestrians // 3
        for i in range(L.pedestrians):
            k = int(rng.integers(n_arms))
            a, e, n = self.arm(k)
            if i < n_cross:
                s = self.junction_clear(k) + 1.6 + float(rng.uniform(-1.2, 1.2))
                lat = float(rng.uniform(-self.hw[k] + 0.8, self.hw[k] - 0.8))
                yaw = math.radians(a) + (math.pi / 2 if rng.uniform() < 0.5 else -math.pi / 2)
                self.pedestrian(e * s + n * lat, yaw, role="crosswalk", arm=k)
            else:
                side = 1 if rng.uniform() < 0.5 else -1
                s = self.corner_start(k, side, self.hw[k] + L.sidewalk) + float(rng.uniform(0, 25))
                lat = side * (self.hw[k] + float(rng.uniform(0.4, L.sidewalk - 0.4)))
                yaw = math.radians(a) + (0 if rng.uniform() < 0.5 else math.pi)
                self.pedestrian(e * s + n * lat, yaw, role="sidewalk", z=0.15, arm=k)

    def pedestrian(self, xy, yaw, role, z=None, **extras):
        if z is None:  # standing on the sidewalk if it is there
            z = 0.15 if self.on_sidewalk(xy) else 0.0
        quad = obb(xy, 0.6, 0.7, yaw)
        if not self.free(quad) or any(overlap(quad, b) for b in self.footprints):
            return None
        self.occupied.append(quad)
        return self.add(f"ped_{self.next_id:03d}", "pedestrian", assets.pedestrian_parts(self.rng), xy, yaw, z=z,
                        role=role, **extras)

    def build(self) -> SceneModel:
        self.static()
        self.place_buildings()
        self.furniture()
        self.road_users()
        extras = {"layout": self.L.description, "arms_deg": self.L.arms}
        return SceneModel(self.name, self.seed, self.actors, self.rigs, extras)


def build_intersection(name: str, seed: int = 0) -> SceneModel:
    if name not in LAYOUTS_SPEC:
        raise KeyError(f"unknown intersection {name!r}")
    return _Builder(name, LAYOUTS_SPEC[name], seed).build()


def build_layout(name: str, layout: Layout, seed: int, key: list[int]) -> SceneModel:
    """The scene ``name`` of any ``layout`` (a procedural draw), its random choices drawn from (``key``, seed)."""
    return _Builder(name, layout, seed, key).build()
