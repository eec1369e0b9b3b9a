"""Check a dataset folder against the spec and report every problem with its path.

``validate(root)`` never raises for bad data: each problem becomes a ``Problem``. Errors
break the contract; warnings are legal but suspicious (a scenario in no split, leftovers
of an interrupted write).
"""
from __future__ import annotations

import math

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import meshes
from .atomic import is_temporary
from .boxes import boxes_overlap
from .camera import check_intrinsics, check_rigid
from .dataset import Dataset, read_json
from .errors import SpecError
from .labels2d import ViewLabels
from .schema import Scenario


@dataclass(frozen=True)
class Problem:
    path: Path
    message: str
    severity: str = "error"  # or "warning"

    def __str__(self) -> str:
        return f"{self.severity}: {self.path}: {self.message}"


class _Report:
    def __init__(self):
        self.problems: list[Problem] = []

    def error(self, path, msg):
        self.problems.append(Problem(Path(path), msg, "error"))

    def warn(self, path, msg):
        self.problems.append(Problem(Path(path), msg, "warning"))


def validate(root: str | Path, check_images: bool = True, progress: bool = False) -> list[Problem]:
    """All problems of the dataset at ``root`` (empty list: valid); ``progress``: a bar over the
    scenarios on stderr."""
    rep = _Report()
    try:
        ds = Dataset.open(root)
    except SpecError as exc:
        rep.error(exc.path or root, exc.message)
        return rep.problems
    names = ds.scenario_names()
    scen_dir = ds.layout.scenarios_dir
    if scen_dir.is_dir():
        for p in sorted(scen_dir.iterdir()):
            if p.is_dir() and p.name not in names:
                rep.error(p, "scenario folder without scenario.json")
    _check_splits(ds, names, rep)
    from tqdm import tqdm

    for name in tqdm(names, desc="validating", unit="scenario", disable=not progress, file=sys.stderr):
        _check_scenario(ds, name, rep, check_images)
    for p in sorted(Path(root).rglob(".*.tmp-*")):
        if is_temporary(p):
            rep.warn(p, "leftover temporary file of an interrupted write (safe to delete)")
    return rep.problems


def _check_splits(ds: Dataset, names: list[str], rep: _Report) -> None:
    for problem in ds.split_problems():
        rep.error(ds.layout.dataset_json, problem)
    seen = set(ds.info.all_split_scenarios)
    for scn in names:
        if scn not in seen:
            rep.warn(ds.layout.scenario_dir(scn), "scenario is in no split")


def _check_scenario(ds: Dataset, name: str, rep: _Report, check_images: bool) -> None:
    path = ds.layout.scenario_json(name)
    try:
        scn = Scenario.from_dict(read_json(path), path)
    except SpecError as exc:
        rep.error(exc.path or path, exc.message)
        return
    if scn.name != name:
        rep.error(path, f"name {scn.name!r} differs from its folder name {name!r}")
    classes = {c.name for c in ds.info.classes}
    actor_ids = {a.id for a in scn.actors}
    for a in scn.actors:
        if a.cls not in classes:
            rep.error(path, f"actor {a.id} ({a.name}) has unknown class {a.cls!r}")
        if a.mesh is not None:
            try:
                meshes.read_mesh(ds.layout.mesh_file(name, a.mesh))
            except SpecError as exc:
                rep.error(exc.path, exc.message)
    _check_road_users_apart(scn, path, rep)
    if not scn.lighting:
        rep.error(path, "no lighting variants")
    if not scn.cameras:
        rep.error(path, "no cameras")
    for cam in scn.cameras:
        where = f"camera {cam.name!r}"
        if (msg := check_intrinsics(cam.K)) is not None:
            rep.error(path, f"{where}: {msg}")
        if (msg := check_rigid(cam.camera_to_world)) is not None:
            rep.error(path, f"{where}: camera_to_world: {msg}")
        if cam.mounted_on is not None and cam.mounted_on not in actor_ids:
            rep.error(path, f"{where}: mounted_on {cam.mounted_on} is not an actor id")
        if not 0 < cam.near < cam.far:
            rep.error(path, f"{where}: needs 0 < near < far")
    if not _check_sequence(ds, scn, rep) or not check_images:
        return
    for frame in range(scn.frames):
        for cam in scn.cameras:
            _check_view(ds, scn, cam, actor_ids, rep, frame)


OVERLAP_TOLERANCE_M = 0.01  # road users' boxes may touch, not overlap by more
CROWD = 200  # road users in one 10 m square: beyond it the scenario is refused before pairs are compared


def _check_road_users_apart(scn: Scenario, path, rep: _Report) -> None:
    """No two road users' (cars', pedestrians') 3D boxes overlap at the scenario's first frame (a generator puts
    nobody where somebody stands). Pairs are compared within 10 m squares: linear in the actors."""
    users = [a for a in scn.actors if a.cls in ("car", "pedestrian") and a.box is not None]
    cells: dict[tuple[int, int], list] = {}
    for a in users:
        cells.setdefault((int(np.floor(a.box.center[0] / 10)), int(np.floor(a.box.center[1] / 10))), []).append(a)
    if max((len(v) for v in cells.values()), default=0) > CROWD:
        rep.error(path, f"more than {CROWD} road users within one 10 m square")
        return
    for (i, j), here in cells.items():
        near = [b for di in (-1, 0, 1) for dj in (-1, 0, 1) for b in cells.get((i + di, j + dj), ())]
        for a in here:
            for b in near:
                if a.id < b.id and boxes_overlap(a.box.center, a.box.size, a.box.yaw, b.box.center, b.box.size,
                                                 b.box.yaw, OVERLAP_TOLERANCE_M):
                    rep.error(path, f"road users {a.id} ({a.name}) and {b.id} ({b.name}) overlap")
                    return


def _check_sequence(ds: Dataset, scn: Scenario, rep: _Report) -> bool:
    """A sequence's frames.json: readable, as many frames as scenario.json says, every road user tracked in
    every frame and no static actor moved, no jump faster than the speed limits, every mounted camera moving
    with its car (the rig is rigid); False when the frames cannot be read (their views are not checked)."""
    path = ds.layout.frames_json(scn.name)
    if scn.frames == 1 and not path.is_file():
        return True
    try:
        seq = ds.sequence(scn.name)
    except SpecError as exc:
        rep.error(exc.path or path, exc.message)
        return False
    if scn.fps is not None and not math.isclose(seq.fps, scn.fps, rel_tol=1e-9):
        rep.error(path, f"fps {seq.fps:g} contradicts scenario.json's {scn.fps:g} (one sequence has one rate)")
    classes = {a.id: a.cls for a in scn.actors}
    detectable = {c.name for c in ds.info.classes if c.detectable}
    tracked = set(seq.tracks)
    stray = sorted(tracked - set(classes))
    if stray:
        rep.error(path, f"tracks {stray[:10]} are not actors of scenario.json")
    static = sorted(a for a in tracked & set(classes) if classes[a] not in detectable)
    if static:
        rep.error(path, f"actors {static[:10]} of a class that is not a road user move: the static scene is the same "
                        "in every frame")
    missing = sorted(a.id for a in scn.actors if a.cls in detectable and a.id not in tracked)
    if missing:
        rep.error(path, f"road users {missing[:10]} have no track (every road user has a pose in every frame)")
    if set(seq.frames[0].cameras) != {c.name for c in scn.cameras}:
        rep.error(path, "its cameras are not scenario.json's")
    first = seq.frames[0]
    moved = sorted(a.id for a in scn.actors if a.id in first.actors and not (
        np.allclose(first.actors[a.id].center, a.box.center, atol=1e-4)
        and abs(math.remainder(first.actors[a.id].yaw - a.box.yaw, 2 * math.pi)) < 1e-4))
    if moved:
        rep.error(path, f"frame 0 of tracks {moved[:10]} is not their box in scenario.json")
    for problem in seq.speed_problems(classes)[:10]:
        rep.error(path, problem)
    for problem in _rig_problems(scn, seq)[:10]:
        rep.error(path, problem)
    return True


def _rig_problems(scn: Scenario, seq) -> list[str]:
    """Cameras that do not move with the car they are mounted on, or move without one (1 cm, 0.1 degree)."""
    out = []
    for cam in scn.cameras:
        car = cam.mounted_on
        if cam.name not in seq.frames[0].cameras or (car is not None and car not in seq.frames[0].actors):
            continue
        for k, fr in enumerate(seq.frames):
            move = seq.motion(car, k) if car is not None else np.eye(4)
            want, got = move @ seq.frames[0].cameras[cam.name], fr.cameras[cam.name]
            if np.abs(want[:3, 3] - got[:3, 3]).max() > 0.01 or np.abs(want[:3, :3] - got[:3, :3]).max() > 2e-3:
                out.append(f"camera {cam.name!r} at frame {k} does not move with car {car}" if car is not None
                           else f"camera {cam.name!r} at frame {k} moves, but it is mounted on no car")
                break
    return out


def _check_view(ds: Dataset, scn: Scenario, cam, actor_ids: set[int], rep: _Report, frame: int = 0) -> None:
    lay = ds.layout
    view = lay.view_dir(scn.name, cam.name, frame)
    if not view.is_dir():
        rep.error(view, "view folder is missing (not rendered?)")
        return
    try:  # a map the dataset declares absent is not looked for
        if ds.info.has("depth"):
            depth = ds.read_depth(scn.name, cam.name, frame)
            if not np.all(np.isfinite(depth)) or depth.min() < 0:
                rep.error(lay.depth(scn.name, cam.name, frame), "depth must be finite and >= 0 (0 = no surface)")
    except SpecError as exc:
        rep.error(exc.path, exc.message)
    try:
        if ds.info.has("instance"):
            inst = ds.read_instance(scn.name, cam.name, frame)
            unknown = sorted(set(np.unique(inst).tolist()) - actor_ids - {0})
            if unknown:
                rep.error(lay.instance(scn.name, cam.name, frame), f"instance ids not in the actor table: {unknown[:20]}")
    except SpecError as exc:
        rep.error(exc.path, exc.message)
    for variant in scn.lighting:
        try:
            ds.read_rgb(scn.name, cam.name, variant.name, frame)
        except SpecError as exc:
            rep.error(exc.path, exc.message)
    labels_path = lay.labels(scn.name, cam.name, frame)
    if not labels_path.exists():
        rep.warn(labels_path, f"no 2D labels for this view (training needs them: project-labels {ds.root})")
    else:
        try:
            labels = ViewLabels.from_dict(read_json(labels_path), labels_path)
        except SpecError as exc:
            rep.error(exc.path, exc.message)
            return
        if (labels.width, labels.height) != (cam.width, cam.height) or labels.camera != cam.name:
            rep.error(labels_path, "labels were made for another camera or resolution")
        if labels.frame != frame:
            rep.error(labels_path, f"labels of frame {labels.frame} in frame {frame}'s folder")
        by_id = {a.id: a for a in scn.actors}
        for o in labels.objects:
            actor = by_id.get(o.instance_id)
            if actor is None:
                rep.error(labels_path, f"label for instance {o.instance_id}, which is not in the actor table")
            elif actor.cls != o.cls:
                rep.error(labels_path, f"instance {o.instance_id} labelled {o.cls!r}, actor table says {actor.cls!r}")
            if o.visible_fraction is not None and not ds.info.has("instance"):
                rep.error(labels_path, f"instance {o.instance_id}: a visible fraction without instance maps to measure it")
            x0, y0, x1, y1 = o.box
            if x0 < -0.5 - 1e-6 or y0 < -0.5 - 1e-6 or x1 > cam.width - 0.5 + 1e-6 or y1 > cam.height - 0.5 + 1e-6:
                rep.error(labels_path, f"instance {o.instance_id}: box {o.box.tolist()} leaves the image")
