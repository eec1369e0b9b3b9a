"""Road users that move (no bpy): the poses of every road user in every frame of a sequence.

The rules (documented for users in docs/guide/data.md):

* Cars drive their routes (``blender_tools.routes``) at a speed of their own, 5-14 m/s, speeding up at
  most ``ACCEL`` and braking at most ``BRAKE`` m/s^2. A car waits at its stop line while its arm's signal
  is red: arms take turns (opposite arms of an even junction together), each green ``GREEN`` s, then
  ``CLEAR`` s all red. Parked cars, vans, buses and trucks stay parked; so do the cars that carry the
  cameras, unless ``moving_cameras`` lets some of them drive (their cameras move with them).
* Pedestrians walk their routes at 1.0-1.6 m/s, speeding up at most ``WALK_ACCEL`` and slowing down at most
  ``WALK_BRAKE`` m/s^2 (within human limits: a walker does not stop dead or halve its pace between frames); a
  quarter of those on sidewalks, and those hiding behind parked vehicles, stand.
* Nobody moves into anyone: a step is taken only where the road user's footprint, lengthened in front by
  what it keeps clear (its stopping distance at its class's braking limit and a gap), is clear of every other
  road user's (theirs lengthened the same way), building, wall, tree trunk and pole. Cars and pedestrians alike
  brake within their limit for what fills the way ahead, for their route's end and for a red signal they can
  still stop for (one they cannot stop for they go through, as on amber); only where nothing within the limits
  is clear does one take a shorter step, or none. So in no frame do two road users' boxes meet or anyone enter a
  building.

The simulation steps at most 0.1 s (nothing passes through anything between frames) and samples the
frames. Deterministic per (scene, seed), from a generator of its own: the scene's build draws the same
numbers with or without motion.

    motion = plan_motion(model, frames=20, fps=5.0, moving_cameras=0)
    motion.poses["ped_031"]          # (20, 4): x, y, z, yaw of the actor's root at each frame
"""
from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field

import numpy as np

from dataset_spec.schema import Scenario
from dataset_spec.sequence import ActorState, FrameState, Sequence, velocities

from .routes import Route, car_route, straight_route, walk_route
from .scene_model import ActorModel, SceneModel
from .street import LAYOUTS_SPEC, Street, obb, overlap

CAR_SPEED, WALK_SPEED = (5.0, 14.0), (1.0, 1.6)
ACCEL, BRAKE = 3.0, 4.0  # m/s^2, a car's
WALK_ACCEL, WALK_BRAKE = 1.0, 2.0  # m/s^2, a pedestrian's (walking gait starts and stops)
GREEN, CLEAR = 8.0, 3.0  # seconds of green per signal phase, then all red
MAX_STEP = 0.1  # seconds per simulation step
STANDING = 0.25  # share of sidewalk pedestrians that stand
MARGIN = 0.02  # metres kept free round a moving footprint
SPARE, WALK_SPARE = 1.0, 0.3  # metres others keep clear beyond a car's (a walker's) stopping distance
OBSTACLE_KINDS = ("building", "wall")
WALL_HEIGHT = 2.5  # metres: what lies lower than this bars the way (not a roof overhanging the sidewalk)


@dataclass
class Footprint:
    """A box footprint in its owner's frame: centre offset (2,), half length, half width."""
    offset: np.ndarray
    half: tuple[float, float]

    @classmethod
    def of(cls, actor: ActorModel, below: float | None = None) -> "Footprint":
        """The footprint of the actor's mesh (of its parts lower than ``below`` metres: a building's walls,
        not the roof that overhangs the sidewalk)."""
        v, _, _ = actor.local_mesh()
        if below is not None and (v[:, 2] < below).any():
            v = v[v[:, 2] < below]
        lo, hi = v[:, :2].min(axis=0), v[:, :2].max(axis=0)
        return cls((lo + hi) / 2, tuple((hi - lo) / 2))

    def quad(self, xy, yaw: float, front: float = 0.0, margin: float = 0.0) -> np.ndarray:
        c, s = math.cos(yaw), math.sin(yaw)
        off = self.offset + np.array([front / 2, 0.0])
        centre = np.asarray(xy, float) + np.array([c * off[0] - s * off[1], s * off[0] + c * off[1]])
        return obb(centre, 2 * (self.half[0] + margin) + front, 2 * (self.half[1] + margin), yaw)


@dataclass
class Mover:
    actor: ActorModel
    foot: Footprint
    route: Route | None = None  # None: stays where it is
    speed: float = 0.0  # wanted speed, m/s
    car: bool = True
    s: float = 0.0  # progress along the route, metres
    v: float = 0.0  # speed now
    xy: np.ndarray = field(default=None)
    yaw: float = 0.0

    def __post_init__(self):
        self.xy = np.array(self.actor.location[:2], float)
        self.yaw = float(self.actor.yaw)

    @property
    def accel(self) -> float:
        return ACCEL if self.car else WALK_ACCEL

    @property
    def brake(self) -> float:
        return BRAKE if self.car else WALK_BRAKE

    @property
    def spare(self) -> float:
        """Metres others keep clear beyond what this road user claims: room for it to brake within its limit."""
        return SPARE if self.car else WALK_SPARE


@dataclass
class Motion:
    fps: float
    frames: int
    poses: dict[str, np.ndarray]  # actor name -> (frames, 4): x, y, z, yaw of its root
    moving: list[str]  # the road users that move at all
    speeds: dict[str, np.ndarray] = field(default_factory=dict)  # actor name -> (frames,) m/s along its route

    def root_pose(self, name: str, frame: int) -> np.ndarray:
        """(4, 4) actor ``name``'s root-to-world at ``frame``."""
        return _pose(self.poses[name][frame])

    def root_motion(self, name: str, frame: int) -> np.ndarray:
        """(4, 4) the rigid move of actor ``name``'s root from frame 0 to ``frame`` (identity if it stays)."""
        if name not in self.poses:
            return np.eye(4)
        return self.root_pose(name, frame) @ np.linalg.inv(self.root_pose(name, 0))

    def sequence(self, scenario: Scenario, names: dict[int, str]) -> Sequence:
        """The spec's frames of ``scenario`` (as exported at frame 0; ``names``: actor id -> actor name of the
        scene): each road user's box and each camera moved rigidly with its (carrying) actor's root."""
        road = [a for a in scenario.actors if a.cls in ("car", "pedestrian")]
        states = [FrameState(f, f / self.fps) for f in range(self.frames)]
        for a in road:
            moves = [self.root_motion(names[a.id], f) for f in range(self.frames)]
            centers = np.array([M[:3, :3] @ a.box.center + M[:3, 3] for M in moves])
            for f, (M, c, v) in enumerate(zip(moves, centers, velocities(centers, self.fps))):
                states[f].actors[a.id] = ActorState(c, math.remainder(a.box.yaw + math.atan2(M[1, 0], M[0, 0]), 2 * math.pi), v)
        for cam in scenario.cameras:
            for f in range(self.frames):
                M = self.root_motion(names.get(cam.mounted_on, ""), f) if cam.mounted_on is not None else np.eye(4)
                states[f].cameras[cam.name] = M @ cam.camera_to_world
        return Sequence(self.fps, states)


def _pose(p) -> np.ndarray:
    """(4, 4) from (x, y, z, yaw)."""
    c, s = math.cos(p[3]), math.sin(p[3])
    return np.array([[c, -s, 0, p[0]], [s, c, 0, p[1]], [0, 0, 1, p[2]], [0, 0, 0, 1.0]])


class Signals:
    """Per-arm signal phases: arm k is green while ``(t + offset) mod cycle`` is in its group's slot."""

    def __init__(self, n_arms: int, offset: float):
        self.groups = 2 if n_arms % 2 == 0 else n_arms
        self.n_arms, self.offset = n_arms, offset

    def green(self, arm: int, t: float) -> bool:
        slot = GREEN + CLEAR
        phase = (t + self.offset) % (self.groups * slot)
        return arm % self.groups == int(phase // slot) and phase % slot < GREEN


def _street(model: SceneModel) -> Street | None:
    from .procedural import is_procedural, layout_of

    base = model.name.split("-s")[0]
    if is_procedural(base):
        return Street(layout_of(base))
    return Street(LAYOUTS_SPEC[base]) if base in LAYOUTS_SPEC else None


def _movers(model: SceneModel, street: Street | None, moving_cameras: int, rng) -> list[Mover]:
    """Every road user, with a route for those that move."""
    rigs = {r.mounted_on for r in sorted(model.cameras, key=lambda r: r.name)[:max(moving_cameras, 0)]}
    out = []
    for a in model.actors:
        if a.cls not in ("car", "pedestrian"):
            continue
        m = Mover(a, Footprint.of(a), car=a.cls == "car")
        drive = a.extras.get("drive")
        if a.cls == "car" and (drive in ("lane", "junction") or (a.name in rigs and drive == "camera")):
            m.speed = float(rng.uniform(*CAR_SPEED))
            if street is None:
                m.route = straight_route(m.xy, m.yaw, m.speed * 60.0)
            else:
                m.route = car_route(street, a.extras["arm"], a.extras.get("lane", 0), a.extras.get("incoming", True),
                                    m.xy, m.foot.half[0])
        elif a.cls == "pedestrian" and a.extras.get("walk", a.extras.get("role") in ("crosswalk", "sidewalk")):
            standing = a.extras.get("role") == "sidewalk" and rng.uniform() < STANDING
            m.speed = 0.0 if standing else float(rng.uniform(*WALK_SPEED))
            if not standing:
                m.route = straight_route(m.xy, m.yaw, m.speed * 60.0) if street is None else \
                    walk_route(street, a.extras["arm"], m.xy, m.yaw)
        m.v = m.speed  # parked cars, camera cars that stay and standing pedestrians keep speed 0
        out.append(m)
    return out


def _obstacles(model: SceneModel) -> list[np.ndarray]:
    """Footprints nobody walks or drives into: buildings and walls whole, tree trunks and poles."""
    out = []
    for a in model.actors:
        kind = a.extras.get("kind")
        if a.cls != "other":
            continue
        if kind in OBSTACLE_KINDS:
            out.append(Footprint.of(a, below=WALL_HEIGHT).quad(a.location[:2], a.yaw))
        elif kind == "tree" or a.name.startswith(("pole_", "sign_")):
            out.append(obb(a.location[:2], 0.4, 0.4, a.yaw))
    return out


class _World:
    """Everyone's footprint now, a moving car's followed by the road it claims along its route (its stopping
    distance and a gap: nobody steps into it), for the clearance test of a step."""

    def __init__(self, movers: list[Mover], obstacles: list[np.ndarray]):
        self.movers = movers
        self.shapes = [_claim(m, m.s, m.v, spare=m.spare) for m in movers] + [[q] for q in obstacles]
        self.centres, self.radii = np.zeros((len(self.shapes), 2)), np.zeros(len(self.shapes))
        for j in range(len(self.shapes)):
            self._bound(j)

    def _bound(self, j: int) -> None:
        pts = np.concatenate(self.shapes[j])
        self.centres[j] = pts.mean(axis=0)
        self.radii[j] = np.linalg.norm(pts - self.centres[j], axis=1).max()

    def clear(self, i: int, shape: list[np.ndarray], bodies_only: bool = False) -> bool:
        """Whether ``shape`` (mover ``i``'s footprint and claimed road) meets no one else's footprint or claimed road
        (``bodies_only``: their footprints alone)."""
        pts = np.concatenate(shape)
        c = pts.mean(axis=0)
        reach = np.linalg.norm(pts - c, axis=1).max()
        near = np.flatnonzero(np.linalg.norm(self.centres - c, axis=1) < self.radii + reach)
        return not any(overlap(a, b) for j in near if j != i for a in shape
                       for b in (self.shapes[j][:1] if bodies_only else self.shapes[j]))

    def move(self, i: int, s: float, v: float) -> None:
        m = self.movers[i]
        m.s, m.v = s, float(v)
        if m.route is not None:
            xy, heading = m.route.at(s)
            m.xy, m.yaw = np.asarray(xy, float), m.yaw if heading is None else float(heading)
        self.shapes[i] = _claim(m, m.s, m.v, spare=m.spare)
        self._bound(i)


def _ahead(m: Mover, v: float) -> float:
    """Metres in front a road user moving at ``v`` keeps clear: its stopping distance at its braking limit and a
    gap (a car's grows with its speed, a pedestrian's is a step)."""
    gap = 1.0 + 0.3 * v if m.car else 0.2
    return gap + v * v / (2 * m.brake)


def _claim(m: Mover, s: float, v: float, margin: float = 0.0, spare: float = 0.0) -> list[np.ndarray]:
    """The footprint of ``m`` at arc length ``s`` of its route (where it stands, without one), followed along the
    route by footprints over what it keeps clear at speed ``v`` and ``spare`` metres more (a car turning claims the
    turn, not the line straight ahead)."""
    if m.route is None or v <= 0:
        return [m.foot.quad(m.xy, m.yaw, 0.0, margin)]
    ahead, out = _ahead(m, v) + spare, []
    n = max(2, math.ceil(ahead / max(m.foot.half[0], 0.1)) + 1)  # footprints overlapping along the claimed road
    for frac in np.linspace(0.0, 1.0, n):
        xy, heading = m.route.at(s + frac * ahead)
        out.append(m.foot.quad(xy, m.yaw if heading is None else heading, 0.0, margin))
    return out


def _stop_speed(gap: float, dt: float, brake: float = BRAKE) -> float:
    """The highest speed from which steps of ``dt``, each ``brake * dt`` slower than the last (the last one to a
    standstill), cover at most ``gap`` metres: with v in [n b, (n + 1) b), b = brake dt, the stop covers
    dt ((n + 1) v - b n (n + 1) / 2)."""
    b, gap = brake * dt, max(gap, 0.0)
    n = 0
    while True:
        v = (gap / dt + b * n * (n + 1) / 2) / (n + 1)
        if v < (n + 1) * b:
            return max(v, n * b)
        n += 1


def _speed_limit(m: Mover, signals: Signals | None, t: float, dt: float) -> tuple[float, float]:
    """(the speed ``m`` may have now, the metres it may go): its wanted speed, braked within its limit for the end
    of its route and for a red signal it can still stop for (one it cannot stop for it goes through, as on amber)."""
    limit, room = m.speed, m.route.length - m.s
    limit = min(limit, _stop_speed(room, dt, m.brake))
    if m.route.stop_at is not None and signals is not None and m.s < m.route.stop_at - 1e-6 \
            and not signals.green(m.route.arm, t):
        gap = m.route.stop_at - m.s
        if m.v <= _stop_speed(gap, dt, m.brake) + m.brake * dt + 1e-6:
            limit, room = min(limit, _stop_speed(gap, dt, m.brake)), min(room, gap)
    return limit, room


def _step(world: _World, i: int, signals: Signals | None, t: float, dt: float) -> None:
    """One simulation step of mover ``i``: the highest speed its class's limits allow (``accel`` up, ``brake``
    down) whose step and claimed way are clear. Where nothing within the limits is clear, a shorter step or none:
    nobody ever moves into anyone."""
    m = world.movers[i]
    if m.route is None or m.s >= m.route.length - 1e-6:
        world.move(i, m.s, 0.0)
        return
    limit, room = _speed_limit(m, signals, t, dt)
    slowest = max(0.0, m.v - m.brake * dt)
    candidates = [max(slowest, min(limit, m.v + m.accel * dt)), min(m.v, limit), slowest]
    tries = [(v, False) for v in dict.fromkeys(max(c, 0.0) for c in candidates)]
    tries.append((candidates[-1], True))  # another's claim is soft: braking into it is allowed where no one stands
    for v, bodies_only in [*tries, *((m.v * f, False) for f in (0.5, 0.25))]:
        ahead = min(v * dt, room)
        if ahead > 1e-9 and world.clear(i, _claim(m, m.s + ahead, v, MARGIN), bodies_only):
            world.move(i, m.s + ahead, ahead / dt)
            return
    world.move(i, m.s, 0.0)


def _start_speeds(world: _World, signals: Signals | None) -> None:
    """Each road user's speed at the first frame: its wanted speed, or the highest below it at which it can still
    stop within its braking limit for what lies ahead (the way it claims clear), its route's end and a red signal."""
    for i, m in enumerate(world.movers):
        if m.route is None or m.v <= 0:
            continue
        v = min(m.v, _speed_limit(m, signals, 0.0, MAX_STEP)[0])
        while v > 0.05 and not world.clear(i, _claim(m, m.s, v, MARGIN)):
            v *= 0.9
        world.move(i, m.s, v if v > 0.05 else 0.0)


def plan_motion(model: SceneModel, frames: int, fps: float, moving_cameras: int = 0) -> Motion:
    """The poses of every road user of ``model`` over ``frames`` frames at ``fps``."""
    if frames < 1 or not fps > 0:
        raise ValueError(f"frames >= 1 and fps > 0, got {frames} and {fps}")
    rng = np.random.default_rng([model.seed, zlib.crc32(model.name.encode()), 1])  # not the build's numbers
    street = _street(model)
    movers = _movers(model, street, moving_cameras, rng)
    signals = Signals(len(street.L.arms), float(rng.uniform(0, 60))) if street is not None else None
    world = _World(movers, _obstacles(model))
    _start_speeds(world, signals)
    z = {m.actor.name: float(m.actor.location[2]) for m in movers}
    poses = {m.actor.name: np.zeros((frames, 4)) for m in movers}
    speeds = {m.actor.name: np.zeros(frames) for m in movers}
    sub = max(1, math.ceil(1.0 / fps / MAX_STEP - 1e-9))
    dt, t = 1.0 / fps / sub, 0.0
    for f in range(frames):
        if f:
            for _ in range(sub):
                t += dt
                for i in range(len(movers)):
                    _step(world, i, signals, t, dt)
        for m in movers:
            height = z[m.actor.name]
            if street is not None and not m.car and m.s > 0:
                height = 0.15 if street.on_sidewalk(m.xy) else 0.0  # off the kerb onto the road and back
            poses[m.actor.name][f] = (m.xy[0], m.xy[1], height, m.yaw)
            speeds[m.actor.name][f] = m.v
    moving = [name for name, p in poses.items() if np.ptp(p, axis=0).max() > 1e-9]
    return Motion(fps, frames, poses, moving, speeds)
