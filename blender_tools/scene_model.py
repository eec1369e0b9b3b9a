"""A declarative scene in plain Python (no bpy): parts, actors, camera rigs, lighting.

Blender is one adapter (``blender_tools.build``) that turns this model into objects; everything
else -- geometry, boxes, camera placement -- is testable without Blender.

Conventions (the spec's world): metres, +Z up. An actor's local frame has +X forward, +Y left,
+Z up, origin on the ground under its centre; its pose is ``location`` (x, y, z) and ``yaw``
(radians about +Z from world +X to the actor's forward axis).

Example::

    car = ActorModel(5, "car_red", "car", parts=car_parts(rng, color=(0.6, 0.05, 0.05)),
                     location=(3.0, -1.75, 0.0), yaw=np.pi)
    rig = CameraRig("cam_0", mounted_on="car_red")
    scene = SceneModel("toy", seed=0, actors=[car, ...], cameras=[rig])
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

SHAPES = ("box", "cylinder", "sphere", "cone")
# Material kinds the Blender adapter knows (see build.MATERIAL_KINDS).
MATERIALS = ("paint", "glass", "rubber", "metal", "asphalt", "concrete", "plaster", "facade", "brick",
             "grass", "foliage", "bark", "marking", "skin", "cloth", "light", "pavement")
CLASSES = ("car", "pedestrian", "other")


@dataclass
class Part:
    """One primitive of an actor, in the actor's local frame.

    ``size``: box (length x, width y, height z); cylinder/cone (diameter x, diameter y, height z)
    along local z before ``rotation``; sphere (diameters). ``location`` is the part's centre.
    ``rotation``: XYZ Euler radians. ``group``: parts of one group become one Blender object;
    the actor's first group is the root object, the others are its children.
    """

    shape: str
    size: tuple[float, float, float]
    location: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    color: tuple[float, float, float] = (0.5, 0.5, 0.5)
    material: str = "plaster"
    group: str = "body"

    def __post_init__(self):
        if self.shape not in SHAPES:
            raise ValueError(f"unknown shape {self.shape!r} (known: {SHAPES})")
        if self.material not in MATERIALS:
            raise ValueError(f"unknown material {self.material!r} (known: {MATERIALS})")


@dataclass
class ActorModel:
    id: int  # instance id (Blender pass_index), 1..32767
    name: str
    cls: str  # 'car' | 'pedestrian' | 'other'
    parts: list[Part]
    location: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw: float = 0.0
    extras: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.cls not in CLASSES:
            raise ValueError(f"actor {self.name}: unknown class {self.cls!r}")
        if not 1 <= self.id <= 32767:
            raise ValueError(f"actor {self.name}: id {self.id} outside 1..32767 (Blender pass_index)")

    @property
    def pose(self) -> np.ndarray:
        """4x4 actor-to-world transform."""
        return pose_matrix(self.location, (0.0, 0.0, self.yaw))

    def groups(self) -> list[str]:
        seen: list[str] = []
        for p in self.parts:
            if p.group not in seen:
                seen.append(p.group)
        return seen

    def local_mesh(self, group: str | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(vertices (N, 3), triangles (M, 3), part index per triangle (M,)) in the actor frame."""
        verts, faces, owner, n = [], [], [], 0
        for i, part in enumerate(self.parts):
            if group is not None and part.group != group:
                continue
            v, f = part_mesh(part)
            verts.append(v)
            faces.append(f + n)
            owner.append(np.full(len(f), i))
            n += len(v)
        if not verts:
            return np.zeros((0, 3)), np.zeros((0, 3), int), np.zeros(0, int)
        return np.concatenate(verts), np.concatenate(faces), np.concatenate(owner)

    def world_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        v, f, _ = self.local_mesh()
        return v @ self.pose[:3, :3].T + self.pose[:3, 3], f


@dataclass
class CameraRig:
    """A forward-facing camera mounted on a car actor (by name).

    ``offset``: position in the car's frame (x forward, y left, z up); ``pitch_deg`` tilts down when
    negative. Lens/sensor/shift follow Blender's camera data.
    """

    name: str
    mounted_on: str
    offset: tuple[float, float, float] = (0.3, 0.35, 1.4)
    pitch_deg: float = -2.0
    lens_mm: float = 24.0
    sensor_width_mm: float = 36.0
    sensor_height_mm: float = 24.0
    sensor_fit: str = "AUTO"
    shift_x: float = 0.0
    shift_y: float = 0.0
    clip_start: float = 0.1
    clip_end: float = 500.0

    def local_matrix(self) -> np.ndarray:
        """Camera-to-car transform with Blender camera axes (looking down -z, y up)."""
        # Blender camera looking along car +X: rotate (90 deg about X) then (-90 deg about Z).
        look = pose_matrix((0, 0, 0), (math.radians(90.0 + self.pitch_deg), 0.0, math.radians(-90.0)))
        look[:3, 3] = self.offset
        return look


@dataclass
class LightingModel:
    name: str
    hdr: str  # file name (a built-in variant's generated EXR or the user's file)
    strength: float = 1.0
    rotation_deg: float = 0.0


@dataclass
class SceneModel:
    name: str
    seed: int
    actors: list[ActorModel]
    cameras: list[CameraRig]
    extras: dict = field(default_factory=dict)

    def actor(self, name: str) -> ActorModel:
        for a in self.actors:
            if a.name == name:
                return a
        raise KeyError(f"scene {self.name}: no actor {name!r}")

    def camera_to_world_blender(self, rig: CameraRig) -> np.ndarray:
        return self.actor(rig.mounted_on).pose @ rig.local_matrix()

    def check(self) -> None:
        ids = [a.id for a in self.actors]
        names = [a.name for a in self.actors]
        if len(set(ids)) != len(ids) or len(set(names)) != len(names):
            raise ValueError(f"scene {self.name}: actor ids and names must be unique")
        if not self.cameras:
            raise ValueError(f"scene {self.name}: no cameras")
        for rig in self.cameras:
            if self.actor(rig.mounted_on).cls != "car":
                raise ValueError(f"camera {rig.name} is mounted on a non-car actor")


# ----------------------------------------------------------------------------- geometry
def rotation_xyz(rx: float, ry: float, rz: float) -> np.ndarray:
    """Rotation matrix of Blender's XYZ Euler (applied X first, then Y, then Z)."""
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def pose_matrix(location, rotation) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotation_xyz(*rotation)
    T[:3, 3] = location
    return T


_BOX_V = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                   [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=np.float64) / 2
_BOX_F = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                   [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


def _unit_shape(shape: str, segments: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Unit primitive centred at the origin, extent [-0.5, 0.5]^3, outward triangles."""
    if shape == "box":
        return _BOX_V, _BOX_F
    ang = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([np.cos(ang) / 2, np.sin(ang) / 2], axis=1)
    if shape in ("cylinder", "cone"):
        top_r = 0.0 if shape == "cone" else 1.0
        bottom = np.column_stack([ring, np.full(segments, -0.5)])
        top = np.column_stack([ring * top_r, np.full(segments, 0.5)])
        v = np.vstack([bottom, top, [[0, 0, -0.5], [0, 0, 0.5]]])
        cb, ct = 2 * segments, 2 * segments + 1
        f = []
        for i in range(segments):
            j = (i + 1) % segments
            f += [[i, j, segments + j], [i, segments + j, segments + i], [cb, j, i], [ct, segments + i, segments + j]]
        return v, np.array(f)
    if shape == "sphere":
        rings = max(3, segments // 2)
        v = [[0, 0, -0.5]]
        for r in range(1, rings):
            th = -np.pi / 2 + np.pi * r / rings
            v += [[np.cos(th) * np.cos(a) / 2, np.cos(th) * np.sin(a) / 2, np.sin(th) / 2] for a in ang]
        v.append([0, 0, 0.5])
        v = np.array(v)
        top = len(v) - 1
        f = [[0, 1 + (i + 1) % segments, 1 + i] for i in range(segments)]
        for r in range(rings - 2):
            b0, b1 = 1 + r * segments, 1 + (r + 1) * segments
            for i in range(segments):
                j = (i + 1) % segments
                f += [[b0 + i, b0 + j, b1 + j], [b0 + i, b1 + j, b1 + i]]
        b = 1 + (rings - 2) * segments
        f += [[b + i, b + (i + 1) % segments, top] for i in range(segments)]
        return v, np.array(f)
    raise ValueError(shape)


def part_mesh(part: Part) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N, 3), triangles (M, 3)) of a part in its actor's frame."""
    v, f = _unit_shape(part.shape)
    v = v * np.asarray(part.size, dtype=np.float64)
    T = pose_matrix(part.location, part.rotation)
    return v @ T[:3, :3].T + T[:3, 3], f.copy()


def oriented_box(points_world: np.ndarray, yaw: float, min_size: float = 0.01):
    """Smallest box with the given yaw containing the points -> (center (3,), size (3,))."""
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    local = np.asarray(points_world, dtype=np.float64) @ R
    lo, hi = local.min(axis=0), local.max(axis=0)
    center = R @ ((lo + hi) / 2)
    return center, np.maximum(hi - lo, min_size)


def _convex_overlap_area(a: np.ndarray, b: np.ndarray) -> float:
    """Area of the intersection of two convex counter-clockwise polygons (k, 2) (Sutherland-Hodgman)."""
    poly = [tuple(p) for p in a]
    for i in range(len(b)):
        (px, py), (qx, qy) = b[i], b[(i + 1) % len(b)]
        side = [(qx - px) * (y - py) - (qy - py) * (x - px) for x, y in poly]
        out = []
        for j, (r, s) in enumerate(zip(poly, poly[1:] + poly[:1])):
            cr, cs = side[j], side[(j + 1) % len(poly)]
            if cr >= 0:
                out.append(r)
            if (cr >= 0) != (cs >= 0):
                t = cr / (cr - cs)
                out.append((r[0] + t * (s[0] - r[0]), r[1] + t * (s[1] - r[1])))
        poly = out
        if len(poly) < 3:
            return 0.0
    x, y = np.array(poly).T
    return 0.5 * abs(float(x @ np.roll(y, -1) - y @ np.roll(x, -1)))


def coincident_faces(actors: list[ActorModel], min_area: float = 1e-4, decimals: int = 5) -> list[tuple]:
    """Pairs of parts with overlapping faces in one plane, facing the same way (world frame).

    Such faces render black in Cycles where both are exposed: a ray leaving one face hits the
    other at distance 0, so no light reaches the shading point (camera rays, and so depth and ids,
    are fine). Returns sorted ``((actor, part index), (actor, part index), normal, offset)``, one per
    pair and shared plane ``normal . x = offset`` (rounded to ``decimals``); overlaps below ``min_area``
    m^2 (edges that only touch) are ignored.
    """
    tris, owners = [], []
    for actor in actors:
        v, f, own = actor.local_mesh()
        v = v @ actor.pose[:3, :3].T + actor.pose[:3, 3]
        tris.append(v[f])
        owners += [(actor.name, int(i)) for i in own]
    if not tris:
        return []
    tri = np.concatenate(tris)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    keep = norm > 1e-12
    tri, n, owners = tri[keep], n[keep] / norm[keep, None], [o for o, k in zip(owners, keep) if k]
    plane = np.round(np.column_stack([n, np.einsum("md,md->m", n, tri[:, 0])]), decimals) + 0.0
    _, group = np.unique(plane, axis=0, return_inverse=True)
    group = group.ravel()
    order = np.argsort(group, kind="stable")
    found = set()
    for idx in np.split(order, np.flatnonzero(np.diff(group[order])) + 1):
        if len({owners[i] for i in idx}) < 2:
            continue
        key = (tuple(plane[idx[0], :3]), float(plane[idx[0], 3]))
        nz = n[idx[0]]
        u = np.cross(nz, [1.0, 0.0, 0.0] if abs(nz[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        p2 = np.stack([tri[idx] @ u, tri[idx] @ np.cross(nz, u)], axis=-1)  # counter-clockwise seen along n
        lo, hi = p2.min(axis=1), p2.max(axis=1)
        for i in range(len(idx)):
            near = np.all(lo[i + 1:] < hi[i], axis=1) & np.all(hi[i + 1:] > lo[i], axis=1)
            for j in np.flatnonzero(near) + i + 1:
                a, b = sorted((owners[idx[i]], owners[idx[j]]))
                if a == b or (a, b, *key) in found or _convex_overlap_area(p2[i], p2[j]) <= min_area:
                    continue
                found.add((a, b, *key))
    return sorted(found)
