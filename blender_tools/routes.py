"""Where road users go in a sequence (no bpy): a route is a polyline on the layout's own geometry
(``blender_tools.street``) that an actor follows at its own speed. ``blender_tools.motion`` moves the
actors along their routes frame by frame.

* **Cars** keep their lane. An incoming car drives to its stop line (where it waits for its arm's green),
  crosses the junction on a smooth curve (a cubic Bezier; round the island, clockwise, on a roundabout)
  to the outgoing lane of the arm most nearly opposite its own, and drives out to that arm's end. An
  outgoing car drives out along its lane. A car inside the junction carries on from where it is.
* **Pedestrians** walk on the sidewalks. One heading for the junction turns at the corner onto the
  crosswalk, crosses, turns again and walks out along the other sidewalk; one on a crosswalk finishes
  crossing and walks out; one heading out walks to the arm's end. A walker turns on a short curve
  (``WALK_TURN`` m), not on the spot, so its pace between frames stays steady through a corner.

    route = car_route(street, k=0, lane=0, incoming=True, xy=(20.0, -1.65), half_length=2.2)
    route.points       # (P, 2) polyline, world metres
    route.stop_at      # arc length where the car waits on red (None: no stop line ahead)
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .street import ARM_LENGTH, Street

STOP_LINE = 3.6  # metres beyond junction_clear where the stop line lies (as intersections draws it)
CROSSWALK = 1.6  # metres beyond junction_clear where the crosswalk's middle lies
END_MARGIN = 4.0  # routes end this far inside an arm's end
WALK_TURN = 0.8  # metres: the radius a pedestrian turns a corner on (less where a leg is short)


@dataclass
class Route:
    points: np.ndarray  # (P, 2)
    stop_at: float | None = None  # arc length of the stop line
    arm: int | None = None  # the arm whose signal the stop line obeys

    def __post_init__(self):
        pts = np.asarray(self.points, float)
        keep = np.r_[True, np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-6]
        self.points = pts[keep]
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        self.cum = np.r_[0.0, np.cumsum(seg)]

    @property
    def length(self) -> float:
        return float(self.cum[-1])

    def at(self, s: float) -> tuple[np.ndarray, float | None]:
        """Position at arc length ``s`` (clamped to the route) and the heading (radians) of its segment
        (None on a route of one point)."""
        if len(self.points) < 2:
            return self.points[0].copy(), None
        s = min(max(s, 0.0), self.length)
        i = int(np.clip(np.searchsorted(self.cum, s, side="right") - 1, 0, len(self.points) - 2))
        d = self.points[i + 1] - self.points[i]
        t = (s - self.cum[i]) / max(self.cum[i + 1] - self.cum[i], 1e-9)
        return self.points[i] + t * d, math.atan2(d[1], d[0])


def opposite_arm(street: Street, k: int) -> int:
    """The arm whose direction is nearest to the reverse of arm ``k`` (the way straight on)."""
    back = street.L.arms[k] + 180.0
    return min((j for j in range(len(street.L.arms)) if j != k),
               key=lambda j: abs((street.L.arms[j] - back + 180.0) % 360.0 - 180.0))


def bezier(p0, d0, p3, d3, n: int = 16) -> np.ndarray:
    """(n, 2) points of the cubic from ``p0`` leaving along unit ``d0`` to ``p3`` arriving along ``d3``."""
    p0, p3 = np.asarray(p0, float), np.asarray(p3, float)
    reach = np.linalg.norm(p3 - p0) / 3
    c1, c2 = p0 + np.asarray(d0) * reach, p3 - np.asarray(d3) * reach
    t = np.linspace(0.0, 1.0, n)[:, None]
    return (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * c1 + 3 * (1 - t) * t ** 2 * c2 + t ** 3 * p3


def rounded(points, radius: float, n: int = 8) -> np.ndarray:
    """``points`` with each corner cut by a curve tangent to both legs ``radius`` of a circle's worth in from the
    corner (less where a leg is shorter than twice that): a road user turns, it does not pivot."""
    pts = np.asarray(points, float)
    out = [pts[:1]]
    for a, b, c in zip(pts[:-2], pts[1:-1], pts[2:]):
        u, v = a - b, c - b
        lu, lv = np.linalg.norm(u), np.linalg.norm(v)
        turn = math.pi - math.acos(float(np.clip(u @ v / max(lu * lv, 1e-12), -1.0, 1.0)))  # 0: straight on
        if lu < 1e-6 or lv < 1e-6 or turn < 1e-3:
            out.append(b[None])
            continue
        cut = min(radius * math.tan(turn / 2), lu / 2, lv / 2)
        out.append(bezier(b + u / lu * cut, -u / lu, b + v / lv * cut, v / lv, n))
    out.append(pts[-1:])
    return np.concatenate(out)


def ring(street: Street, p0, p3, n: int = 24) -> np.ndarray:
    """(n, 2) points round a roundabout's island, clockwise (the island on the driver's right), from the
    angle of ``p0`` to that of ``p3``."""
    radius = street.L.roundabout + 3.5
    a0, a3 = math.atan2(p0[1], p0[0]), math.atan2(p3[1], p3[0])
    sweep = (a0 - a3) % (2 * math.pi)
    ang = a0 - np.linspace(0.0, sweep, n)
    return radius * np.stack([np.cos(ang), np.sin(ang)], axis=1)


def car_route(street: Street, k: int, lane: int, incoming: bool, xy, half_length: float) -> Route:
    """The route of a car on arm ``k`` in lane ``lane`` now at ``xy`` (its box centre)."""
    _, e, n = street.arm(k)
    xy = np.asarray(xy, float)
    if not incoming:
        lat = float(xy @ n)
        return Route([xy, e * (ARM_LENGTH - END_MARGIN - half_length) + n * lat])
    j = opposite_arm(street, k)
    _, ej, nj = street.arm(j)
    lat_in = street.lane_lateral(k, lane, True)
    lat_out = street.lane_lateral(j, min(lane, street.lanes[j] - 1), False)
    stop_s = street.junction_clear(k) + STOP_LINE + half_length + 0.5
    p0 = e * stop_s + n * lat_in
    p3 = ej * (street.junction_clear(j) + half_length) + nj * lat_out
    end = ej * (ARM_LENGTH - END_MARGIN - half_length) + nj * lat_out
    before = float(xy @ e) > stop_s
    start = p0 if before else xy
    heading = -e if before else -e  # lanes run straight: a car in the junction still heads along its arm
    if street.L.roundabout:  # onto the ring and off it along curves, not round a corner
        arc = ring(street, start, p3)
        tangent = lambda q: np.array([q[1], -q[0]]) / max(np.linalg.norm(q), 1e-9)  # noqa: E731 - clockwise
        curve = np.concatenate([bezier(start, heading, arc[2], tangent(arc[2]), 8), arc[3:-3],
                                bezier(arc[-3], tangent(arc[-3]), p3, ej, 8)])
    else:
        curve = bezier(start, heading, p3, ej)
    pts = np.concatenate([[xy], curve, [end]]) if before else np.concatenate([curve, [end]])
    route = Route(pts)
    stop_at = float(np.linalg.norm(p0 - xy)) if before else None
    return Route(route.points, stop_at, k if before else None)


def walk_route(street: Street, k: int, xy, yaw: float) -> Route:
    """The route of a pedestrian at ``xy`` near arm ``k`` facing ``yaw``."""
    _, e, n = street.arm(k)
    xy = np.asarray(xy, float)
    s, lat = float(xy @ e), float(xy @ n)
    hw, walk = street.hw[k], street.L.sidewalk
    side = 1.0 if lat >= 0 else -1.0
    far = ARM_LENGTH - END_MARGIN
    head = np.array([math.cos(yaw), math.sin(yaw)])
    cross_s = street.junction_clear(k) + CROSSWALK
    kerb = hw + min(0.6, walk / 2)  # where a crossing pedestrian steps onto the far sidewalk
    if abs(lat) < hw:  # on the road: a crosswalk
        to = -1.0 if head @ n < 0 else 1.0
        other = to * (hw + walk / 2)
        return Route(rounded([xy, e * s + n * to * kerb, e * s + n * other, e * far + n * other], WALK_TURN))
    if head @ e < 0:  # on a sidewalk, heading for the junction: turn onto the crosswalk, cross, walk out
        at = max(cross_s, min(s, cross_s))
        other = -side * abs(lat)
        return Route(rounded([xy, e * at + n * lat, e * at + n * other, e * far + n * other], WALK_TURN))
    return Route([xy, e * far + n * lat])


def straight_route(xy, yaw: float, distance: float) -> Route:
    """Straight on along ``yaw`` for ``distance`` metres (scenes without a street, the toy)."""
    xy = np.asarray(xy, float)
    return Route([xy, xy + distance * np.array([math.cos(yaw), math.sin(yaw)])])
