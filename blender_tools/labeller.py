"""Auto-labelling of a Blender scene: instance ids (``pass_index``) and classes for every object.

Works the same on procedural scenes and on user ``.blend`` files. The convention:

* **Actors.** An actor is a top-level object together with all its descendants (a car made of a
  body, wheels and windows is one actor with one id). An object with the custom property
  ``label_actor = True`` starts its own actor even when it has a parent.
* **Classes.** From the collection an actor's root is in (or any collection above it):
  ``Cars`` -> car, ``Pedestrians`` -> pedestrian (``Car``/``Vehicles``/``People``/``Persons``
  are accepted too); everything else -> other (ground, road, buildings, walls, trees...).
  Overrides, strongest first: custom property ``label_class`` (``car``/``pedestrian``/``other``)
  on the root, then a root name starting with ``car.``/``car_`` or ``ped.``/``ped_``.
* **Ids.** Custom property ``label_id`` (1..32767) on the root keeps an id; other actors get
  the next free ids in name order, so ids are stable as long as names are.
* **Cameras** are parented (directly or through empties) to the car that carries them; a camera
  without a car gets ``mounted_on = None``.

``label_scene`` reports what it could not classify (unknown ``label_class`` values, objects whose
name says car/person but that sit outside the class collections, a class conflict inside one
actor, duplicate ``label_id``) -- those objects still get an id and class 'other'/root class.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from ._bpy import require_bpy

CLASS_COLLECTIONS = {"cars": "car", "car": "car", "vehicles": "car",
                     "pedestrians": "pedestrian", "pedestrian": "pedestrian", "people": "pedestrian",
                     "persons": "pedestrian"}
NAME_PREFIXES = {"car.": "car", "car_": "car", "ped.": "pedestrian", "ped_": "pedestrian"}
CLASSES = ("car", "pedestrian", "other")
GEOMETRY_TYPES = {"MESH", "CURVE", "SURFACE", "META", "FONT", "CURVES", "POINTCLOUD", "VOLUME"}
SUSPICIOUS_WORDS = {"car": "car", "vehicle": "car", "person": "pedestrian", "pedestrian": "pedestrian",
                    "human": "pedestrian", "walker": "pedestrian"}
MAX_PASS_INDEX = 32767


@dataclass
class LabelledActor:
    id: int
    name: str
    cls: str
    root: object  # bpy Object
    objects: list = field(default_factory=list)  # geometry objects (root's hierarchy)


@dataclass
class LabelResult:
    actors: list[LabelledActor]
    cameras: list  # (camera object, mounted_on actor id or None)
    problems: list[str]

    def by_id(self) -> dict[int, LabelledActor]:
        return {a.id: a for a in self.actors}


def _actor_root(obj):
    while obj.parent is not None and not bool(obj.get("label_actor", False)):
        obj = obj.parent
    return obj


def _collection_class(obj, parents_of) -> str | None:
    todo = list(obj.users_collection)
    seen = set()
    while todo:
        c = todo.pop()
        if c.name in seen:
            continue
        seen.add(c.name)
        base = c.name.split(".")[0].strip().lower()
        if base in CLASS_COLLECTIONS:
            return CLASS_COLLECTIONS[base]
        todo += parents_of.get(c.name, [])
    return None


def _actor_class(root, name: str, parents_of: dict, problems: list[str]) -> str:
    """An actor's class: its root's ``label_class``, else its collection's, else its name's prefix, else
    'other' (with a note when its name suggests a road user)."""
    override = root.get("label_class")
    if override is not None:
        if str(override) in CLASSES:
            return str(override)
        problems.append(f"{name}: unknown label_class {override!r} (use one of {CLASSES}); labelled 'other'")
        return "other"
    cls = _collection_class(root, parents_of)
    if cls is None:
        cls = next((c for p, c in NAME_PREFIXES.items() if name.lower().startswith(p)), None)
    if cls is None:
        cls = "other"
        hint = next((c for w, c in SUSPICIOUS_WORDS.items() if w in name.lower()), None)
        if hint:
            problems.append(f"{name}: name suggests '{hint}' but it is in no '{'Cars' if hint == 'car' else 'Pedestrians'}' "
                            "collection and has no label_class; labelled 'other'")
    return cls


def label_scene(scene=None) -> LabelResult:
    """Assign ``pass_index`` and a class to every renderable object of ``scene``."""
    bpy = require_bpy()
    scene = scene or bpy.context.scene
    parents_of: dict[str, list] = {}
    for c in bpy.data.collections:
        for child in c.children:
            parents_of.setdefault(child.name, []).append(c)
    problems: list[str] = []
    groups: dict[str, list] = {}
    roots = {}
    for obj in scene.objects:
        if obj.type not in GEOMETRY_TYPES or obj.hide_render:
            continue
        root = _actor_root(obj)
        groups.setdefault(root.name, []).append(obj)
        roots[root.name] = root
    actors: list[LabelledActor] = []
    used: set[int] = set()
    pending = []
    for name in sorted(groups):
        root = roots[name]
        cls = _actor_class(root, name, parents_of, problems)
        for obj in groups[name]:
            ocls = _collection_class(obj, parents_of)
            if obj is not root and ocls is not None and ocls != cls:
                problems.append(f"{obj.name}: in a '{ocls}' collection but part of actor {name} ({cls}); labelled {cls}")
        actor = LabelledActor(0, name, cls, root, sorted(groups[name], key=lambda o: o.name))
        want = root.get("label_id")
        if want is not None and isinstance(want, int) and 1 <= want <= MAX_PASS_INDEX and want not in used:
            actor.id = int(want)
            used.add(actor.id)
        else:
            if want is not None:
                problems.append(f"{name}: label_id {want!r} is invalid or taken; assigned a new id")
            pending.append(actor)
        actors.append(actor)
    next_id = 1
    for actor in pending:
        while next_id in used:
            next_id += 1
        if next_id > MAX_PASS_INDEX:
            raise ValueError(f"more than {MAX_PASS_INDEX} actors: Blender's pass_index cannot hold more ids")
        actor.id = next_id
        used.add(next_id)
    for actor in actors:
        for obj in actor.objects:
            obj.pass_index = actor.id
    actors.sort(key=lambda a: a.id)
    by_root = {a.root.name: a.id for a in actors}
    cameras = []
    for obj in sorted(scene.objects, key=lambda o: o.name):
        if obj.type != "CAMERA":
            continue
        mount = None
        p = obj.parent
        while p is not None:
            if p.name in by_root and p.type in GEOMETRY_TYPES:
                mount = by_root[p.name]
            p = p.parent
        mount_actor = next((a for a in actors if a.id == mount), None)
        if mount_actor is not None and mount_actor.cls != "car":
            problems.append(f"camera {obj.name}: mounted on {mount_actor.name} ({mount_actor.cls}), not a car")
        cameras.append((obj, mount))
    return LabelResult(actors, cameras, problems)
