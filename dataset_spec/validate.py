"""Check a dataset folder against the spec and report every problem with its path.

``validate(root)`` never raises for bad data: each problem becomes a ``Problem``. Errors
break the contract; warnings are legal but suspicious (a scenario in no split, leftovers
of an interrupted write).
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import meshes
from .atomic import is_temporary
from .camera import check_intrinsics, check_rigid
from .dataset import Dataset, read_json
from .errors import SpecError
from .labels2d import ViewLabels
from .schema import SPLIT_NAMES, Scenario


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
    path = ds.layout.dataset_json
    seen: dict[str, str] = {}
    for split in SPLIT_NAMES:
        for scn in ds.info.splits.get(split, []):
            if scn in seen:
                rep.error(path, f"scenario {scn!r} is in both '{seen[scn]}' and '{split}' splits (leaks between splits)")
            seen[scn] = split
            if scn not in names:
                rep.error(path, f"split '{split}' names scenario {scn!r}, which does not exist")
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
        if check_images:
            _check_view(ds, scn, cam, actor_ids, rep)


def _check_view(ds: Dataset, scn: Scenario, cam, actor_ids: set[int], rep: _Report) -> None:
    lay = ds.layout
    view = lay.view_dir(scn.name, cam.name)
    if not view.is_dir():
        rep.error(view, "view folder is missing (not rendered?)")
        return
    try:  # a map the dataset declares absent is not looked for
        if ds.info.has("depth"):
            depth = ds.read_depth(scn.name, cam.name)
            if not np.all(np.isfinite(depth)) or depth.min() < 0:
                rep.error(lay.depth(scn.name, cam.name), "depth must be finite and >= 0 (0 = no surface)")
    except SpecError as exc:
        rep.error(exc.path, exc.message)
    try:
        if ds.info.has("instance"):
            inst = ds.read_instance(scn.name, cam.name)
            unknown = sorted(set(np.unique(inst).tolist()) - actor_ids - {0})
            if unknown:
                rep.error(lay.instance(scn.name, cam.name), f"instance ids not in the actor table: {unknown[:20]}")
    except SpecError as exc:
        rep.error(exc.path, exc.message)
    for variant in scn.lighting:
        try:
            ds.read_rgb(scn.name, cam.name, variant.name)
        except SpecError as exc:
            rep.error(exc.path, exc.message)
    labels_path = lay.labels(scn.name, cam.name)
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
