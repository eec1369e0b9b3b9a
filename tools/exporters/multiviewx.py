"""Renders in the MultiviewX layout, for MVDet-family tools: one folder per scenario (each scenario's
cameras are a rig of their own: they sit on other cars in every scene). A sequence gives one folder per
lighting variant, ``<scenario>__<variant>``, whose frames are the sequence's (the rig must stand still:
a sequence whose camera cars drive is refused); a scenario of one frame gives one folder whose frames
are its lighting variants (the same people under each HDR environment)::

    OUT/<scenario>/Image_subsets/C<k>/<frame, 4 digits>.png       camera k-1 of the scenario
    OUT/<scenario>/annotations_positions/<frame, 5 digits>.json   personID, positionID, views (-1: not in it)
    OUT/<scenario>/calibrations/intrinsic/intr_Camera<k>.xml       camera_matrix (cv2.FileStorage)
    OUT/<scenario>/calibrations/extrinsic/extr_Camera<k>.xml       rvec, tvec (metres, world to camera)
    OUT/<scenario>/gt.txt                                          frame grid_x grid_y, every person
    OUT/<scenario>/visibility/<frame, 5 digits>.json               per person and view: visible fraction...
    OUT/<scenario>/config.json                                     GMVD's rig description of the scene
    OUT/<scenario>/rectangles.pom                                  each position's box in each camera (POM, GMVD)
    OUT/<scenario>/README.md                                       the grid, the frames, the cameras

The ground grid has MultiviewX's 2.5 cm cells and position = x + NX * y, with its (0, 0) corner at the
world's origin as MultiviewX has it; the exported world is this dataset's shifted so that the corner
covers every person with a 2 m margin (the README states the shift and ``NX x NY``). A person's box in
a view is its amodal label box where the label is ground truth, else -1; the visibility file (which
the field's formats have no place for) gives every label of the person. ``classes`` may add cars.

MVDet's and GMVD's MultiviewX loaders read six cameras (``Camera1`` ... ``Camera6``), so a rig of more (a procedural
layout has 3-8 camera cars) is exported as its first ``MVDET_CAMERAS`` cameras, which the README names;
``max_cameras=None`` exports them all (for a tool told the count).
"""
from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from dataset_spec import Dataset, LabelThresholds
from dataset_spec.atomic import atomic_write_json, atomic_write_text
from dataset_spec.ground_grid import GroundGrid
from dataset_spec.names import JoinedNames, below
from dataset_spec.rig_formats import FORMATS, camera_name, extrinsics_of, write_annotation, write_extrinsics, write_intrinsics

from dataset_spec.cli_support import UserError

from .common import check_images, copy_file, export_variants
from .pom import write_pom

FMT = FORMATS["multiviewx"]
MARGIN_M = 2.0
MVDET_CAMERAS = 6  # the cameras MVDet's and GMVD's MultiviewX loaders list (Camera1..6)


def scenario_grid(centres_xy: np.ndarray, cell_m: float = FMT.grid.cell_m) -> tuple[GroundGrid, np.ndarray]:
    """A grid of ``cell_m`` cells from a corner (whole metres) ``MARGIN_M`` beyond the people; returns it
    (origin at 0: the exported world) and the corner in this dataset's world (the shift)."""
    lo = np.floor(centres_xy.min(axis=0) - MARGIN_M) if len(centres_xy) else np.zeros(2)
    hi = np.ceil(centres_xy.max(axis=0) + MARGIN_M) if len(centres_xy) else np.full(2, 2 * MARGIN_M)
    nx, ny = (int(math.ceil((hi[k] - lo[k]) / cell_m)) for k in range(2))
    return GroundGrid(nx, ny, cell_m), lo


def export_multiviewx(ds: Dataset, out_dir: str | Path, scenarios: list[str] | None = None,
                      thresholds: LabelThresholds | None = None, variant: str | None = "all",
                      classes: tuple[str, ...] = ("pedestrian",), max_cameras: int | None = MVDET_CAMERAS) -> Path:
    """Write MultiviewX-layout folders under ``out_dir`` (see the module docstring): one per scenario of one
    frame (its lighting variants the frames), one per sequence and lighting variant (its frames the frames);
    ``variant`` None or "all": every lighting variant, else that one; ``max_cameras``: the first that many of each
    rig's cameras (None: all); returns ``out_dir``."""
    out = Path(out_dir)
    names = scenarios if scenarios is not None else ds.scenario_names()
    variant = "all" if variant is None else variant
    check_rigs(ds, names)
    check_images(ds, names, variant)
    joined = JoinedNames("MultiviewX rig folder")  # every folder's name checked before the first is written
    folders = {(n, v): joined(n, *([v] if ds.scenario(n).frames > 1 else [])) for n in names
               for v in export_variants(ds, n, variant)}
    for name in names:
        variants = export_variants(ds, name, variant)
        if ds.scenario(name).frames == 1:
            _write_rig(ds, name, below(out, folders[name, variants[0]]), [(0, v) for v in variants], thresholds,
                       (classes, max_cameras))
        else:
            for var in variants:
                _write_rig(ds, name, below(out, folders[name, var]), [(f, var) for f in ds.frames(name)], thresholds,
                           (classes, max_cameras))
    return out


def gmvd_config(cameras: list, grid: GroundGrid, frames: int) -> dict:
    """GMVD's description of a scene's rig (``config.json``): cameras, frames, image and grid shapes (rows,
    columns), the cell in metres, the grid's origin and the region it covers in metres (y, x)."""
    cam = cameras[0]
    return {"num_cam": len(cameras), "num_frames": frames, "img_shape": [cam.height, cam.width],
            "grid_shape": [grid.ny, grid.nx], "grid_cell": grid.cell_m, "origin": [0, 0],
            "region_size": [round(grid.ny * grid.cell_m, 6), round(grid.nx * grid.cell_m, 6)]}


def check_rigs(ds: Dataset, names: list[str]) -> None:
    """A one-line error for a sequence whose cameras move: MultiviewX has one calibration per rig."""
    for name in names:
        moving = _moving_cameras(ds, name)
        if moving:
            raise UserError(f"multiviewx: the cameras of {name} move ({', '.join(moving[:3])}): the format has one "
                            "calibration per rig (render with parked camera cars, --moving-cameras 0)")


def _moving_cameras(ds: Dataset, name: str) -> list[str]:
    """The cameras of a scenario whose pose changes over its frames (1 mm, 0.01 degree)."""
    seq = ds.sequence(name)
    first = seq.frames[0].cameras
    return sorted(c for c in first if any(not np.allclose(f.cameras[c], first[c], atol=2e-4) for f in seq.frames))


def _write_rig(ds: Dataset, name: str, folder: Path, frames: list[tuple[int, str]], thresholds, what) -> None:
    """One MultiviewX folder: ``frames`` as (frame of the sequence, lighting variant), exported frame by frame;
    ``what``: (the classes exported, the most cameras)."""
    classes, max_cameras = what
    scn = ds.scenario(name)
    cameras = scn.cameras[:max_cameras]
    ids = [a.id for a in scn.actors if a.cls in classes]
    seq = ds.sequence(name)
    everywhere = np.array([fr.actors[i].center[:2] if i in fr.actors else scn.actor(i).box.center[:2]
                           for fr in seq.frames[:max(f for f, _ in frames) + 1] for i in ids]).reshape(-1, 2)
    grid, shift = scenario_grid(everywhere)
    to_export = np.eye(4)
    to_export[:2, 3] = -shift
    for k, cam in enumerate(cameras):
        cal = folder / "calibrations"
        write_intrinsics(cal / "intrinsic" / f"intr_{camera_name(FMT, k)}.xml", cam.K)
        write_extrinsics(cal / "extrinsic" / f"extr_{camera_name(FMT, k)}.xml",
                         *extrinsics_of(to_export @ cam.camera_to_world, FMT), FMT)
    rows = []
    for n, (frame, var) in enumerate(frames):
        entries, seen, cells = _frame_people(ds, (name, frame, len(cameras)), ids, grid, shift, thresholds, classes)
        for k, cam in enumerate(cameras):
            copy_file(ds.layout.rgb(name, cam.name, var, frame), folder / "Image_subsets" / f"C{k + 1}" / f"{n:04d}.png")
        write_annotation(folder / "annotations_positions" / f"{n:05d}.json", entries)
        atomic_write_text(folder / "visibility" / f"{n:05d}.json", json.dumps(seen, indent=1))
        rows += [f"{n} {x} {y}\n" for x, y in cells]
    atomic_write_text(folder / "gt.txt", "".join(rows))
    atomic_write_json(folder / "config.json", gmvd_config(cameras, grid, len(frames)))
    write_pom(folder / "rectangles.pom", [replace(c, camera_to_world=to_export @ c.camera_to_world) for c in cameras],
              grid)
    atomic_write_text(folder / "README.md", _readme(name, grid, shift, frames, seq.fps if scn.frames > 1 else None,
                                                    ([c.name for c in cameras], len(scn.cameras))))


def _frame_people(ds: Dataset, at: tuple[str, int, int], ids: list[int], grid: GroundGrid, shift: np.ndarray,
                  thresholds, classes) -> tuple[list, list, np.ndarray]:
    """One frame's annotation entries, visibility records and grid cells of the people ``ids``; ``at``: (scenario,
    frame, the cameras exported: the first that many)."""
    name, frame, n_cameras = at
    scn = ds.scenario_at(name, frame)
    people = [scn.actor(i) for i in ids]
    cells = grid.xy_of_world(np.array([a.box.center[:2] - shift for a in people]).reshape(-1, 2))
    positions = grid.position_of_xy(cells)
    labels = [ds.read_labels(name, cam.name, frame) for cam in scn.cameras[:n_cameras]]
    kept = [{o.instance_id for o in vl.kept(thresholds)} for vl in labels]
    entries, seen = [], []
    for a, pos in zip(people, positions):
        views, vis = [], []
        for k, vl in enumerate(labels):
            lab = next((o for o in vl.objects if o.instance_id == a.id), None)
            box = lab.box if lab is not None and a.id in kept[k] else [-1] * 4
            views.append({"viewNum": k, **{key: float(v) if v != -1 else -1
                                           for key, v in zip(("xmin", "ymin", "xmax", "ymax"), box)}})
            if lab is not None:
                vis.append({"viewNum": k, "visible_fraction": lab.visible_fraction,
                            "in_frame_fraction": lab.in_frame_fraction, "occlusion_level": lab.occlusion_level,
                            "visible_pixels": lab.visible_pixels, "ground_truth": a.id in kept[k]})
        entry = {"personID": a.id, "positionID": int(pos), "views": views}
        if classes != ("pedestrian",):
            entry["class"] = a.cls
        entries.append(entry)
        seen.append({"personID": a.id, "class": a.cls, "views": vis})
    return entries, seen, cells


def _readme(name: str, grid: GroundGrid, shift: np.ndarray, frames: list[tuple[int, str]], fps: float | None,
            rig: tuple[list[str], int]) -> str:
    cameras, of = rig
    chosen = "" if len(cameras) == of else (f" (the first {len(cameras)} of the rig's {of}: MVDet's and GMVD's loaders "
                                            "read six; `--multiviewx-cameras all` exports every one)")
    if fps is None:
        what = "Frames (all with the same people): " + ", ".join(f"{n} = lighting '{v}'" for n, (_, v) in enumerate(frames))
    else:
        what = (f"Frames: the sequence's frames 0..{len(frames) - 1} at {fps:g} fps (frame n is at {1 / fps:g} * n s), "
                f"lighting '{frames[0][1]}'; the people keep their personID (track id) in every frame")
    return f"""# {name} in the MultiviewX layout

Written by `project-labels --export multiviewx` (tools/exporters/multiviewx.py).

- Ground grid: {grid.nx} x {grid.ny} cells of {grid.cell_m * 100:g} cm ({grid.nx * grid.cell_m:g} m x {grid.ny * grid.cell_m:g} m),
  position = x + {grid.nx} * y, world X = x * {grid.cell_m:g}, Y = y * {grid.cell_m:g} (metres), z up.
  MultiviewX's own grid is 1000 x 640: give tools this grid's size (MVDet: `worldgrid_shape = [{grid.ny}, {grid.nx}]`).
- The world is the source dataset's moved by ({-shift[0]:g}, {-shift[1]:g}) m: its point (0, 0) is the grid's corner.
- {what}.
- Cameras (fixed over the frames): {", ".join(f"C{k + 1} = {c}" for k, c in enumerate(cameras))}{chosen}.
- `visibility/<frame>.json`: per person and view its visible fraction (0: fully hidden), in-frame
  fraction, KITTI occlusion level, visible pixels and whether it is ground truth there; a box of -1 in
  `annotations_positions` means not ground truth in that view (out of frame, too far or too small).
- `config.json`: the rig as GMVD describes a scene (cameras, frames, image and grid shape, cell size).
- `rectangles.pom`: each grid position's box in each camera (a 0.16 m x 1.8 m cylinder standing there; a
  position some camera sees is listed for every camera, `notvisible` where that one does not), what GMVD's
  varying-camera evaluation reads.
- Back into a dataset: `dataset-spec import multiviewx THIS_FOLDER --out DATASET --grid {grid.nx},{grid.ny}`.
"""
