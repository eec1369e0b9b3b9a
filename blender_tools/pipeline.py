"""Render jobs (bpy side): load a scene, label it, export the scenario, render its views.

A ``Job`` is plain JSON so the CLI can run it in-process or hand it to a worker process
(``python -m blender_tools.worker JOB.json``). Events (plain dicts) go to an ``emit`` callback:

* ``{"event": "plan", "views": [[camera, n_files_missing], ...]}`` once after loading
* ``{"event": "warning", "message": ...}``  labeller reports
* ``{"event": "file", "camera": ..., "kind": "data"|variant, "render_s": ...}`` after each file
* ``{"event": "done", "render_s": total Cycles time, "wall_s": ...}``

Resumable: a view's files are written atomically, each only when missing (or ``force``); a kill
loses at most the render in flight. Worker ``index`` of ``n_workers`` takes cameras
``sorted(names)[index::n_workers]``; worker 0 also writes ``scenario.json`` and the meshes.
"""
from __future__ import annotations

import os
import re
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from dataset_spec import Dataset, DatasetInfo, LightingVariant, Scenario
from dataset_spec.atomic import process_alive
from dataset_spec.dataset import missing_view_files
from dataset_spec.errors import SpecError

from ._bpy import require_bpy
from .render import RenderSettings


TEMP_PREFIX = "blender_gen_"  # render scratch folders in $TMPDIR: blender_gen_<pid>_<random>


def remove_stale_temp_dirs(base: str | Path | None = None) -> int:
    """Delete scratch folders of render processes that no longer run (a kill leaves them behind);
    returns how many were removed."""
    removed = 0
    for path in Path(base or tempfile.gettempdir()).glob(f"{TEMP_PREFIX}*"):
        m = re.fullmatch(rf"{TEMP_PREFIX}(\d+)_.*", path.name)
        if not (m and path.is_dir()) or process_alive(int(m.group(1))):
            continue
        shutil.rmtree(path, ignore_errors=True)
        removed += 1
    return removed


class JobError(Exception):
    """A problem with the job's input (reported to the user in one line)."""


@dataclass
class Job:
    out: str
    scenario: str  # catalog name, or the scenario name for a .blend
    seed: int = 0
    blend: str | None = None
    variants: list[dict] = field(default_factory=list)  # {name, hdr, path, strength, rotation_deg}
    settings: dict = field(default_factory=dict)  # RenderSettings fields
    force: bool = False
    index: int = 0
    n_workers: int = 1
    # files (relative to the dataset folder) complete elsewhere: a render farm task writing into its
    # own scratch folder skips them as if they were there (blender_tools.ray_farm)
    skip: list[str] = field(default_factory=list)
    frames: int = 1  # a sequence of this many frames (1: one instant)
    fps: float = 10.0
    moving_cameras: int = 0  # camera cars that drive (the rest stay parked)

    def to_dict(self) -> dict:
        return asdict(self)


def load_scene(job: Job):
    """Fill the (reset) Blender session with the job's scene; returns (metadata for scenario extras, the
    ``Motion`` of a sequence or None, the actors' root objects by name)."""
    bpy = require_bpy()
    from .build import build_scene, reset_blender
    from .render import quiet_stdout

    reset_blender()
    if job.blend:
        path = Path(job.blend)
        if not path.is_file():
            raise JobError(f"--blend {path}: no such file")
        try:
            with quiet_stdout():
                bpy.ops.wm.open_mainfile(filepath=str(path), load_ui=False)
        except RuntimeError as exc:
            raise JobError(f"--blend {path}: Blender cannot read it ({str(exc).strip().splitlines()[-1]})") from None
        return {"generator": "blender_tools (user .blend)", "blend": str(path.resolve())}, None, {}
    from .motion import plan_motion
    from .scenarios import build_model

    model = build_model(job.scenario, job.seed)
    roots = build_scene(model)
    motion = plan_motion(model, job.frames, job.fps, job.moving_cameras) if job.frames > 1 else None
    return {"generator": "blender_tools.scenarios", "seed": model.seed, **model.extras}, motion, roots


def pose_frame(motion, roots: dict, frame: int) -> None:
    """Move the scene's moving actors (their cameras with them) to ``frame``; nothing else is touched."""
    bpy = require_bpy()
    from .build import _matrix

    for name in motion.moving:
        roots[name].matrix_world = _matrix(motion.root_pose(name, frame))
    bpy.context.view_layer.update()


def run_job(job: Job, emit) -> None:
    bpy = require_bpy()
    from .export import camera_info
    from .labeller import label_scene
    from .render import Renderer

    t0 = time.perf_counter()
    meta, motion, roots = load_scene(job)
    labels = label_scene()
    for msg in labels.problems:
        emit({"event": "warning", "message": msg})
    if not labels.cameras:
        raise JobError(f"scene {job.scenario}: no cameras (add camera objects parented to cars)")
    if not labels.actors:
        raise JobError(f"scene {job.scenario}: no objects to label")
    settings = RenderSettings(**job.settings)
    tmp = tempfile.mkdtemp(prefix=f"{TEMP_PREFIX}{os.getpid()}_")
    try:
        try:
            renderer = Renderer(settings, tmp)
        except RuntimeError as exc:
            if "--device gpu" in str(exc):
                raise JobError(str(exc)) from None
            raise
        scene = bpy.context.scene
        ds = Dataset.create(job.out, DatasetInfo(name=Path(job.out).name))
        name = job.scenario
        cams = sorted(labels.cameras, key=lambda c: c[0].name)
        infos = {obj.name: camera_info(obj, scene, mount) for obj, mount in cams}
        made = [i.name for i in infos.values()]
        if len(set(made)) != len(made):
            clash = next(n for n in made if made.count(n) > 1)
            raise JobError(f"two cameras of the scene are both named {clash!r} once made legal (letters, digits, "
                           "'_', '-', '.'): rename one in the .blend")
        variants = [LightingVariant(v["name"], v["hdr"], v["strength"], v["rotation_deg"]) for v in job.variants]
        if job.index == 0:
            scn = write_scenario(ds, name, labels, scene, list(infos.values()), variants, meta, job.force, motion)
            if motion is not None:
                ds.write_sequence(name, motion.sequence(scn, {a.id: a.name for a in labels.actors}))
        mine = cams[job.index::job.n_workers]
        frames = motion.frames if motion is not None else 1
        plan = [[(obj, mount, _missing(ds, name, infos[obj.name], variants, job.force, set(job.skip), f))
                 for obj, mount in mine] for f in range(frames)]
        emit({"event": "plan", "views": [[infos[obj.name].name, sum(len(p[i][2]) for p in plan)]
                                         for i, (obj, _) in enumerate(mine)]})
        for f, views in enumerate(plan):
            if not any(missing for _, _, missing in views):
                continue
            if motion is not None:
                pose_frame(motion, roots, f)
            for obj, mount, missing in views:
                _render_view(ds, renderer, job, name, infos[obj.name].name, obj, labels.by_id(), mount, missing, f,
                             emit)
        emit({"event": "done", "render_s": renderer.render_seconds, "wall_s": time.perf_counter() - t0})
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _render_view(ds: Dataset, renderer, job: Job, name: str, view: str, obj, by_id: dict, mount, missing: list,
                 frame: int, emit) -> None:
    """Render what ``missing`` lists of one view at ``frame``: the data pass, then each lighting variant."""
    if not missing:
        return
    hidden = by_id[mount].objects if mount is not None else []
    for o in hidden:  # a car's own body is not seen by its camera (still casts shadows)
        o.visible_camera = False
    try:
        if "data" in missing:
            before = renderer.render_seconds
            depth, inst = renderer.render_data(obj)
            ds.write_depth(name, view, depth, frame)
            ds.write_instance(name, view, inst, frame)
            emit({"event": "file", "camera": view, "kind": "data", "frame": frame,
                  "render_s": renderer.render_seconds - before})
        for v in job.variants:
            if v["name"] not in missing:
                continue
            before = renderer.render_seconds
            renderer.set_lighting(v["path"], v["strength"], v["rotation_deg"])
            ds.write_rgb(name, view, v["name"], renderer.render_rgb(obj), frame)
            emit({"event": "file", "camera": view, "kind": v["name"], "frame": frame,
                  "render_s": renderer.render_seconds - before})
    finally:
        for o in hidden:
            o.visible_camera = True


def _missing(ds: Dataset, scenario: str, cam, variants: list[LightingVariant], force: bool,
             skip: set[str] = frozenset(), frame: int = 0) -> list[str]:
    """Which files of a view still need rendering: 'data' (depth + instance) and variant names.
    Existing files are decoded and checked against the camera's resolution, so a truncated or
    garbage file (a disk error, a user's copy) is rendered again rather than trusted; files in
    ``skip`` (relative paths) count as complete."""
    names = [v.name for v in variants]
    if force:
        return ["data", *names]
    lay = ds.layout
    rel = lambda p: str(p.relative_to(lay.root))  # noqa: E731
    missing = missing_view_files(lay, scenario, cam, names, frame=frame)
    rgb = lambda m: rel(lay.rgb(scenario, cam.name, m, frame))  # noqa: E731
    if {rel(lay.depth(scenario, cam.name, frame)), rel(lay.instance(scenario, cam.name, frame))} <= skip \
            and "data" in missing:
        missing = [m for m in missing if m != "data" and rgb(m) not in skip]
    return [m for m in missing if m == "data" or rgb(m) not in skip]


def write_scenario(ds: Dataset, name: str, labels, scene, cameras, variants, meta: dict, force: bool,
                   motion=None) -> Scenario:
    """Write scenario.json and actor meshes (at frame 0); keep earlier lighting variants and occlusion stats."""
    from .export import export_actors

    old = None
    if ds.layout.scenario_json(name).is_file() and not force:
        try:
            old = ds.scenario(name)
        except SpecError:
            old = None
    actors = export_actors(labels, scene, write_mesh=lambda aid, v, f: ds.write_mesh(name, aid, v, f))
    frames, fps = (motion.frames, motion.fps) if motion is not None else (1, None)
    scn = merge_scenario(old, Scenario(name, actors, cameras, list(variants), dict(meta), frames, fps))
    ds.write_scenario(scn)
    if motion is None:
        ds.layout.frames_json(name).unlink(missing_ok=True)  # an earlier sequence's frames are not this one's
    return scn


def merge_scenario(old: Scenario | None, new: Scenario) -> Scenario:
    """``new`` keeping what an earlier render of the same cameras recorded: its other lighting
    variants and its extras (occlusion statistics), the new ones winning (variants sorted by name)."""
    lighting, extras = list(new.lighting), dict(new.extras)
    if old is not None:
        same_cams = len(old.cameras) == len(new.cameras) and all(
            a.name == b.name and a.width == b.width and np.allclose(a.K, b.K) for a, b in zip(old.cameras, new.cameras))
        if same_cams:
            have = {v.name for v in lighting}
            lighting = [v for v in old.lighting if v.name not in have] + lighting
            extras = {**old.extras, **new.extras}
    lighting.sort(key=lambda v: v.name)
    return replace(new, lighting=lighting, extras=extras)
