"""A scenario's frames in time (spec 1.2, ``frames.json``): each frame's time, every road user's box pose
and velocity (world, m/s), every camera's pose. The actor id is the track id: the same ids in every
frame. The static scene (buildings, the road, parked things not listed here) is ``scenario.json``'s and
identical in every frame::

    seq = ds.sequence("intersection_07")     # a one-frame scenario has a Sequence of one frame too
    seq.fps, len(seq.frames), seq.seconds
    state = seq.frames[3].actors[12]          # ActorState: center (3,), yaw, velocity (3,)
    seq.frames[3].cameras["cam_0"]            # (4, 4) camera-to-world at frame 3
    seq.motion(12, 3)                         # (4, 4) the rigid move of actor 12 from frame 0 to frame 3

A velocity is the displacement to the next frame over the frame interval (the last frame's: from the
one before), the rate a constant-velocity prediction uses.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import SpecError
from .names import excerpt
from .schema import SPEC_VERSION, Fields, Scenario

# Fastest plausible speeds (m/s) of each class: a jump between frames faster than this is a defect of the data.
SPEED_LIMITS = {"car": 25.0, "pedestrian": 4.0}


@dataclass
class ActorState:
    center: np.ndarray  # (3,) box centre, world metres
    yaw: float  # radians about +Z (the box's)
    velocity: np.ndarray  # (3,) m/s

    def to_dict(self, actor_id: int) -> dict:
        return {"id": actor_id, "center": np.asarray(self.center, float).tolist(), "yaw": float(self.yaw),
                "velocity": np.asarray(self.velocity, float).tolist()}


@dataclass
class FrameState:
    index: int
    time_s: float
    actors: dict[int, ActorState] = field(default_factory=dict)  # actor (track) id -> state
    cameras: dict[str, np.ndarray] = field(default_factory=dict)  # camera name -> (4, 4) camera-to-world

    def to_dict(self) -> dict:
        return {"index": self.index, "time_s": self.time_s,
                "actors": [s.to_dict(aid) for aid, s in sorted(self.actors.items())],
                "cameras": [{"name": n, "camera_to_world": np.asarray(m, float).tolist()}
                            for n, m in sorted(self.cameras.items())]}

    @classmethod
    def from_fields(cls, f: Fields) -> "FrameState":
        actors = {}
        for a in f.items("actors"):
            aid = a.get("id", int)
            if aid in actors:
                raise a.err("id", f"actor {aid} twice in one frame")
            actors[aid] = ActorState(a.position("center", (3,)), a.get("yaw", float), a.array("velocity", (3,)))
        cameras = {}
        for c in f.items("cameras"):
            name = c.name("name")
            if name in cameras:
                raise c.err("name", f"camera {excerpt(name)} twice in one frame")
            cameras[name] = c.position("camera_to_world", (4, 4))
        return cls(f.get("index", int), f.get("time_s", float), actors, cameras)


@dataclass
class Sequence:
    fps: float
    frames: list[FrameState]

    @property
    def seconds(self) -> float:
        return self.frames[-1].time_s - self.frames[0].time_s if self.frames else 0.0

    @property
    def tracks(self) -> list[int]:
        """The actor (track) ids every frame lists."""
        return sorted(self.frames[0].actors) if self.frames else []

    def motion(self, actor_id: int, frame: int) -> np.ndarray:
        """(4, 4) the rigid motion (a turn about +Z and a shift) taking actor ``actor_id``'s box from frame 0
        to ``frame``: applied to its frame-0 mesh or corners, it gives them at ``frame``."""
        a, b = self.frames[0].actors[actor_id], self.frames[frame].actors[actor_id]
        return _pose(b.center, b.yaw) @ np.linalg.inv(_pose(a.center, a.yaw))

    def move(self, actor_id: int, frame: int, points: np.ndarray) -> np.ndarray:
        """(N, 3) world points of actor ``actor_id`` at frame 0 (its mesh, its box corners) where they are at
        ``frame`` (unchanged for an actor the sequence does not list)."""
        if frame == 0 or actor_id not in self.frames[frame].actors:
            return np.asarray(points, float)
        M = self.motion(actor_id, frame)
        return np.asarray(points, float) @ M[:3, :3].T + M[:3, 3]

    def to_dict(self) -> dict:
        return {"spec_version": SPEC_VERSION, "fps": self.fps, "frames": [f.to_dict() for f in self.frames]}

    @classmethod
    def from_dict(cls, obj: Any, path=None) -> "Sequence":
        f = Fields(obj, path)
        fps = f.get("fps", float)
        if not fps > 0:
            raise f.err("fps", "must be > 0")
        seq = cls(fps, [FrameState.from_fields(ff) for ff in f.items("frames")])
        problem = seq.problem()
        if problem:
            raise SpecError(path, problem)
        return seq

    def problem(self) -> str | None:
        """What breaks the sequence's own rules (None: nothing): frames in order, time increasing, the
        same tracks and cameras in every frame."""
        if not self.frames:
            return "frames: a sequence has at least one frame"
        first = self.frames[0]
        for k, fr in enumerate(self.frames):
            if fr.index != k:
                return f"frames[{k}].index is {fr.index}, not {k} (frames in order, from 0)"
            if k and not fr.time_s > self.frames[k - 1].time_s:
                return f"frames[{k}].time_s {fr.time_s} does not increase (after {self.frames[k - 1].time_s})"
            if set(fr.actors) != set(first.actors):
                gone = sorted(set(first.actors) ^ set(fr.actors))
                return f"frames[{k}]: track ids differ from frame 0's ({excerpt(gone)}): ids persist in every frame"
            if set(fr.cameras) != set(first.cameras):
                return f"frames[{k}]: cameras differ from frame 0's"
        return None

    def speed_problems(self, classes: dict[int, str]) -> list[str]:
        """Jumps between frames faster than ``SPEED_LIMITS`` allow (``classes``: actor id -> class name)."""
        out = []
        for k in range(1, len(self.frames)):
            dt = self.frames[k].time_s - self.frames[k - 1].time_s
            for aid, state in self.frames[k].actors.items():
                limit = SPEED_LIMITS.get(classes.get(aid, ""), max(SPEED_LIMITS.values()))
                step = float(np.linalg.norm(state.center[:2] - self.frames[k - 1].actors[aid].center[:2]))
                if step > limit * dt + 1e-6:
                    out.append(f"actor {aid} moves {step:.2f} m in {dt:.3f} s between frames {k - 1} and {k} "
                               f"(faster than {limit:g} m/s)")
        return out


def _pose(center, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = center
    return T


def still_sequence(scenario: Scenario, classes: set[str]) -> Sequence:
    """The one-frame sequence of a scenario without ``frames.json``: its road users (``classes``) at rest."""
    actors = {a.id: ActorState(np.asarray(a.box.center, float), float(a.box.yaw), np.zeros(3))
              for a in scenario.actors if a.cls in classes}
    cameras = {c.name: np.asarray(c.camera_to_world, float) for c in scenario.cameras}
    return Sequence(1.0, [FrameState(0, 0.0, actors, cameras)])


def velocities(centers: np.ndarray, fps: float) -> np.ndarray:
    """(F, 3) centres over F frames -> (F, 3) velocities: the displacement to the next frame over the frame
    interval, the last frame's from the one before (zero for a single frame)."""
    centers = np.asarray(centers, float)
    if len(centers) < 2:
        return np.zeros_like(centers)
    step = np.diff(centers, axis=0) * fps
    return np.concatenate([step, step[-1:]], axis=0)

