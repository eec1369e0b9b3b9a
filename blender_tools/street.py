"""A layout's street geometry (no bpy): its road arms, lanes, parking strips, sidewalks, the junction and
its crosswalks, in the world frame (metres, +Z up, the junction at the origin). The builder of
``blender_tools.intersections`` places the static world and the road users on it; the motion rules of
a sequence move road users along it.

    street = Street(LAYOUTS_SPEC["intersection_07"])
    a, e, n = street.arm(0)              # angle (deg), unit direction along the arm, its left normal
    street.junction_clear(0)             # metres along arm 0 beyond which both kerbs clear the junction
    street.lane_lateral(0, 0, True)      # lateral offset of arm 0's first incoming lane (right-hand traffic)
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

ARM_LENGTH = 55.0
LANE = 3.3
PARKING = 2.3
ROAD_STEP = 0.001  # height step between overlapping road arms (no coincident faces, see static())
# Overlapping faces in one plane facing the same way render black in Cycles (shadow and bounce rays
# leaving one face hit the other at distance 0; see scene_model.coincident_faces). So:
BUILDING_GAP = 0.05  # between the bodies of buildings in a row (their roof slabs still overlap ...)
BUILDING_STAGGER = (0.02, 0.08)  # ... so each front is set back this much more (per building)
MARK_INSET = 0.15  # markings end this far inside the road's edges (their sides never touch a road side)


@dataclass
class Layout:
    description: str
    arms: list[float]  # degrees
    lanes: list[int] | int = 1  # lanes per direction, per arm or for all
    parking: bool = True
    sidewalk: float = 3.0
    setback: float = 1.0
    heights: tuple[float, float] = (7.0, 18.0)
    cameras: int = 5
    pedestrians: int = 14
    moving: int = 5
    parked: int = 8
    big: list[str] = field(default_factory=lambda: ["van", "bus"])
    roundabout: float = 0.0  # central island radius (0: none)
    trees: int = 6
    walls: int = 2
    brick: float = 0.3  # share of brick facades
    crosswalks: bool = True  # zebra stripes across each arm at the junction


LAYOUTS_SPEC = {
    "intersection_01": Layout("4-way cross, one lane each way, parking both sides", [0, 90, 180, 270]),
    "intersection_02": Layout("T-junction with a parked bus and a delivery van", [0, 90, 180], cameras=4,
                              big=["bus", "van", "van"]),
    "intersection_03": Layout("skewed 4-way junction (70 deg)", [0, 70, 180, 250], cameras=5, big=["truck", "van"]),
    "intersection_04": Layout("wide avenue (2 lanes each way) crossing a side street", [0, 90, 180, 270],
                              lanes=[2, 1, 2, 1], cameras=6, moving=7, big=["bus", "truck", "van"], heights=(12, 24)),
    "intersection_05": Layout("narrow old-town crossing, tall brick facades, no setback", [0, 90, 180, 270],
                              parking=False, sidewalk=1.8, setback=0.0, heights=(9, 16), cameras=4, pedestrians=16,
                              moving=3, parked=2, big=["van"], trees=0, walls=0, brick=0.8),
    "intersection_06": Layout("roundabout with four arms and a planted island", [0, 90, 180, 270], roundabout=7.0,
                              cameras=5, big=["bus", "van"], trees=4),
    "intersection_07": Layout("busy 4-way cross: bus, vans and truck parked near crosswalks, crowded sidewalks",
                              [0, 90, 180, 270], cameras=6, pedestrians=18, moving=6, parked=10,
                              big=["bus", "van", "van", "truck"], heights=(8, 20)),
    "intersection_08": Layout("Y-junction (120 deg arms)", [0, 120, 240], cameras=4, big=["van", "truck"]),
    "intersection_09": Layout("T-junction on a wide avenue", [0, 90, 180], lanes=[2, 1, 2], cameras=5, moving=6,
                              big=["bus", "van"], heights=(10, 22)),
    "intersection_10": Layout("five-arm star junction", [0, 72, 144, 216, 288], cameras=8, pedestrians=16,
                              big=["van", "van", "bus"], parked=10, trees=4),
    "intersection_11": Layout("skewed T-junction (60 deg) with walls and trees", [0, 60, 180], cameras=3,
                              big=["truck", "van"], trees=8, walls=4),
    "intersection_12": Layout("offset-free plaza crossing with many pedestrians", [0, 90, 180, 270], cameras=7,
                              pedestrians=24, moving=4, parked=6, sidewalk=5.0, big=["van", "bus"], trees=8),
}
LAYOUTS = {name: spec.description for name, spec in LAYOUTS_SPEC.items()}


# ----------------------------------------------------------------------------- 2D helpers
def direction(deg: float) -> np.ndarray:
    return np.array([math.cos(math.radians(deg)), math.sin(math.radians(deg))])


def obb(center, length, width, yaw) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    ex, ey = np.array([c, s]) * length / 2, np.array([-s, c]) * width / 2
    center = np.asarray(center, dtype=float)
    return np.array([center + ex + ey, center - ex + ey, center - ex - ey, center + ex - ey])


def overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Separating-axis test of two convex quads (4, 2)."""
    for poly in (a, b):
        for i in range(4):
            edge = poly[(i + 1) % 4] - poly[i]
            axis = np.array([-edge[1], edge[0]])
            pa, pb = a @ axis, b @ axis
            if pa.max() < pb.min() or pb.max() < pa.min():
                return False
    return True


class Street:
    """The geometry of one layout: ``hw[k]`` is arm k's half width (lanes and parking), ``lanes[k]`` its
    lanes per direction."""

    def __init__(self, layout: Layout):
        self.L = layout
        n = len(layout.arms)
        lanes = layout.lanes if isinstance(layout.lanes, list) else [layout.lanes] * n
        self.lanes = lanes
        self.hw = [l * LANE + (PARKING if layout.parking else 0.0) for l in lanes]

    def arm(self, k):
        a = self.L.arms[k]
        e = direction(a)
        return a, e, np.array([-e[1], e[0]])

    def gaps(self, k) -> tuple[float, float]:
        """Angle (deg) to the next arm counter-clockwise (left side) and clockwise (right side)."""
        arms = self.L.arms
        n = len(arms)
        left = (arms[(k + 1) % n] - arms[k]) % 360 or 360
        right = (arms[k] - arms[(k - 1) % n]) % 360 or 360
        return left, right

    def corner_start(self, k, side: int, width: float) -> float:
        """Distance along arm k where a strip at lateral ``width`` on ``side`` (+1 left) clears the junction."""
        gap = self.gaps(k)[0 if side > 0 else 1]
        if gap >= 179.0:
            s = 0.0
        else:
            s = width / math.tan(math.radians(gap) / 2)
        if self.L.roundabout:
            s = max(s, self.L.roundabout + 6.5 + 1.0)
        return s

    def junction_clear(self, k) -> float:
        """Distance along arm k beyond which both kerbs are clear of the junction."""
        return max(self.corner_start(k, s, self.hw[k] + self.L.sidewalk) for s in (1, -1))

    def in_roads(self, pts: np.ndarray, margin: float) -> bool:
        """True if any point is within (half width + sidewalk + margin) of an arm or on the roundabout."""
        for j in range(len(self.L.arms)):
            _, e, n = self.arm(j)
            s, lat = pts @ e, pts @ n
            lim = self.hw[j] + self.L.sidewalk + margin
            if np.any((s > -lim) & (np.abs(lat) < lim)):
                return True
        if self.L.roundabout and np.any(np.linalg.norm(pts, axis=1) < self.L.roundabout + 6.5 + self.L.sidewalk):
            return True
        return False

    def lane_lateral(self, k, lane: int, incoming: bool) -> float:
        """Lateral offset (arm frame) of a lane centre; incoming traffic drives on the right = -n side."""
        off = (lane + 0.5) * LANE
        return -off if incoming else off

    def on_sidewalk(self, xy) -> bool:
        for k in range(len(self.L.arms)):
            _, e, n = self.arm(k)
            s, lat = float(np.dot(xy, e)), abs(float(np.dot(xy, n)))
            if s > 0 and self.hw[k] <= lat <= self.hw[k] + self.L.sidewalk:
                return True
        return False
