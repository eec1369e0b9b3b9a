"""A Wildtrack- or MultiviewX-format folder as a dataset of this project (``dataset-spec import``)::

    summary = import_rig("wildtrack", "Wildtrack", "out/wildtrack")      # all checked before writing
    summary["box_error_px"]     # median |annotated box - projected standing cylinder| over every box

Each annotated frame becomes a scenario of the camera rig (``frame_<number>``), each person a
pedestrian standing on its grid position (a 0.32 m x 0.32 m x 1.8 m box: the cylinder MultiviewX
draws its boxes from), and each annotated box a label kept as given (clipped to the image; the box
as annotated in ``extras.annotated_box``). Such data has no depth or instance maps and no per-view
visibility: ``dataset.json`` lists the maps ``absent`` and labels carry ``visible_fraction: null``.
The world keeps the dataset's axes in metres; if its z axis points down (the annotated boxes say
so) it is turned half a turn about x so that z is up, and ``extras.source.world_from_source``
records the transform. Split: the first 90 % of frames train, the rest test (``val``: a share of
the training frames, from their end). Lens distortion (the real MultiviewX has a little) is the
user's choice: ``ignore`` it as MVDet does (the summary says how far it moves the image corners), or
``undistort`` the images with OpenCV and write the K of the undistorted images, the annotated boxes
moved with them. Frames may be PNG or JPEG.
"""
from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from .atomic import staged_folder
from .boxes import clip_box_to_image, frustum_fraction
from .camera import points_to_camera, project_camera_points
from .cli_support import UserError
from .dataset import Dataset
from .ground_grid import GroundGrid
from .images import read_rgb, write_rgb
from .rig_formats import FORMATS, Rig, RigFormat, read_rig
from .labels2d import Label2D, LabelThresholds, ViewLabels
from .schema import Actor, Box3D, CameraInfo, DatasetInfo, LightingVariant, Scenario

PERSON_RADIUS_M, PERSON_HEIGHT_M = 0.16, 1.8  # MultiviewX's box cylinder (FACTS.md)
VARIANT = "original"  # the one lighting variant of camera data
NEAR_M, FAR_M = 0.1, 200.0
# the imported boxes are the ground truth as annotated: no in-frame, size or distance cut
THRESHOLDS = LabelThresholds(min_in_frame=0.0, min_box_pixels=1.0)
HALF_TURN_X = np.diag([1.0, -1.0, -1.0, 1.0])  # z down -> z up, keeping the axes right-handed


def cylinder_points(ground_xy: np.ndarray, height: float, n: int = 16) -> np.ndarray:
    """(P, 2*n, 3) points on the bottom and top circles of standing cylinders at ``ground_xy`` (P, 2)."""
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([np.cos(a), np.sin(a)], axis=1) * PERSON_RADIUS_M
    pts = []
    for z in (0.0, height):
        xy = ground_xy[:, None, :] + ring[None]
        pts.append(np.concatenate([xy, np.full(xy.shape[:2] + (1,), z)], axis=2))
    return np.concatenate(pts, axis=1)


def cylinder_box(camera_to_world: np.ndarray, K: np.ndarray, points: np.ndarray) -> np.ndarray | None:
    """The unclipped image box of one cylinder's points, None unless all lie in front of the camera."""
    cam = points_to_camera(camera_to_world, points)
    if cam[:, 2].min() <= NEAR_M:
        return None
    uv = project_camera_points(K, cam)
    return np.array([uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()])


def box_errors(rig: Rig, grid: GroundGrid, height: float) -> np.ndarray:
    """Per annotated box: the mean absolute difference (px) of its four sides from the projection of
    the person's standing cylinder of ``height`` (negative: the world's z points down)."""
    errors = []
    for frame in rig.frames:
        for person in frame.people:
            xy = grid.world_of_xy(grid.xy_of_position([person.position_id]))
            pts = cylinder_points(xy, height)[0]
            for v, box in person.views.items():
                cam = rig.cameras[v]
                proj = cylinder_box(cam.camera_to_world, cam.K, pts)
                if proj is not None:
                    errors.append(float(np.abs(proj - box).mean()))
    return np.asarray(errors)


def frame_splits(names: list[str], val: float = 0.0, test: float = 0.1) -> dict[str, list[str]]:
    """The datasets' own split: the last ``test`` share of the frames (in order) test, the rest train;
    ``val``: that share of all frames taken from the end of the training frames."""
    n = len(names)
    n_test = int(round(test * n)) if n > 1 else 0
    n_val = min(int(round(val * n)), n - n_test - 1) if val > 0 else 0
    n_train = n - n_test - n_val
    return {"train": names[:n_train], "val": names[n_train:n_train + n_val], "test": names[n_train + n_val:]}


DISTORTION_MODES = ("ignore", "undistort")


def corner_shift(K: np.ndarray, dist: np.ndarray, width: int, height: int) -> float:
    """The largest distance (px) lens distortion moves an image corner: what ignoring it costs there."""
    if not np.abs(dist).max(initial=0.0):
        return 0.0
    corners = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], np.float64)
    moved = cv2.undistortPoints(corners.reshape(-1, 1, 2), K, dist, P=K).reshape(-1, 2)
    return float(np.linalg.norm(moved - corners, axis=1).max())


def undistorted(rig: Rig) -> tuple[Rig, list]:
    """``rig`` as its undistorted images show it: each camera with the K OpenCV gives the undistorted
    image (``getOptimalNewCameraMatrix``, alpha 0: no black border) and no distortion, every annotated
    box the box of its undistorted outline; and per camera the maps that undistort its images (None:
    none needed)."""
    cams, maps = [], []
    for cam in rig.cameras:
        if not np.abs(cam.distortion).max(initial=0.0):
            cams.append(cam)
            maps.append(None)
            continue
        size = (cam.width, cam.height)
        K = cv2.getOptimalNewCameraMatrix(cam.K, cam.distortion, size, 0, size)[0]
        maps.append(cv2.initUndistortRectifyMap(cam.K, cam.distortion, None, K, size, cv2.CV_32FC1))
        cams.append(replace(cam, K=K, distortion=np.zeros(0)))
    t = np.linspace(0.0, 1.0, 9)
    frames = []
    for frame in rig.frames:
        people = []
        for person in frame.people:
            views = {}
            for v, box in person.views.items():
                old = rig.cameras[v]
                if maps[v] is None:
                    views[v] = box
                    continue
                x0, y0, x1, y1 = box
                outline = np.concatenate([np.stack([x0 + t * (x1 - x0), np.full_like(t, y)], 1) for y in (y0, y1)]
                                         + [np.stack([np.full_like(t, x), y0 + t * (y1 - y0)], 1) for x in (x0, x1)])
                uv = cv2.undistortPoints(outline.reshape(-1, 1, 2), old.K, old.distortion, P=cams[v].K).reshape(-1, 2)
                views[v] = np.array([uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()])
            people.append(replace(person, views=views))
        frames.append(replace(frame, people=people))
    return replace(rig, cameras=cams, frames=frames), maps


def lens_plan(rig: Rig, distortion: str) -> tuple[Rig, list, dict]:
    """The rig to import under ``distortion`` (``ignore``: as given, as MVDet reads it; ``undistort``:
    ``undistorted``), the maps for each camera's images, and a summary (the largest corner shift)."""
    if distortion not in DISTORTION_MODES:
        raise UserError(f"--distortion {distortion!r}: one of {', '.join(DISTORTION_MODES)}")
    shifts = [(corner_shift(c.K, c.distortion, c.width, c.height), c.name) for c in rig.cameras]
    worst, name = max(shifts)
    info = {"mode": distortion, "max_corner_shift_px": worst, "camera": name if worst else None}
    if distortion == "undistort":
        rig, maps = undistorted(rig)
        return rig, maps, info
    return rig, [None] * len(rig.cameras), info


def import_rig(format_name: str, src: str | Path, out: str | Path, grid: GroundGrid | None = None,
               val: float = 0.0, progress: bool = False, distortion: str = "ignore") -> dict:
    """Write the dataset at ``out`` (which must not hold one) from the folder ``src``; returns a summary
    (frames, people, boxes, the median box error in pixels, whether z was turned, the lens distortion).
    Everything is written into a temporary folder first and moved into ``out`` at the end: a failure
    on any frame leaves ``out`` as it was."""
    if format_name not in FORMATS:
        raise UserError(f"unknown format {format_name!r}; known: {', '.join(FORMATS)}")
    if not 0.0 <= val < 0.9:
        raise UserError(f"--val {val}: a share of the frames in [0, 0.9)")
    fmt: RigFormat = FORMATS[format_name]
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise UserError(f"--out {out}: exists and is not empty (import writes a new dataset)")
    grid = grid or fmt.grid
    rig, maps, lens = lens_plan(read_rig(fmt, src, grid), distortion)
    up, down = box_errors(rig, grid, PERSON_HEIGHT_M), box_errors(rig, grid, -PERSON_HEIGHT_M)
    if not len(up):
        raise UserError(f"{src}: no annotated box lies in front of its camera: the calibration does not fit the "
                        "annotations (another format, or other units?)")
    z_down = float(np.median(down)) < float(np.median(up))
    world_from_source = HALF_TURN_X if z_down else np.eye(4)
    names = [f"frame_{f.number:0{fmt.annotation_digits}d}" for f in rig.frames]
    source = {"format": fmt.name, "folder": str(Path(src).resolve()), "grid": {
        "nx": grid.nx, "ny": grid.ny, "cell_m": grid.cell_m, "origin_m": list(grid.origin_m)},
        "world_from_source": world_from_source.tolist(), "frames": {n: f.number for n, f in zip(names, rig.frames)},
        "distortion": lens}
    info = DatasetInfo(name=fmt.name, splits=frame_splits(names, val), absent=["depth", "instance"],
                       extras={"source": source})
    cameras = [CameraInfo(c.name, c.width, c.height, c.K, world_from_source @ c.camera_to_world, None, NEAR_M, FAR_M,
                          {"rvec": c.rvec.tolist(), "tvec": c.tvec.tolist(), "distortion": c.distortion.tolist()})
               for c in rig.cameras]
    with staged_folder(out) as tmp:
        boxes = _write_frames(Dataset.create(tmp, info), rig, names, cameras, maps, grid, world_from_source, progress)
    return {"frames": len(rig.frames), "cameras": len(cameras), "people": sum(len(f.people) for f in rig.frames),
            "boxes": boxes, "box_error_px": float(np.median(down if z_down else up)), "z_turned": z_down,
            "splits": {k: len(v) for k, v in info.splits.items()}, "distortion": lens}


MAX_SOURCE_CELLS = 1 << 26  # an imported grid's nx x ny (MultiviewX's is 1000 x 640)


def read_source(extras: dict, where: str) -> dict | None:
    """An imported dataset's ``extras.source`` (its ground grid, the turn from the source's world, its frames)
    checked where it is read, a dataset being a file from others: one line for the first thing wrong; None where
    the dataset has none."""
    source = extras.get("source") if isinstance(extras, dict) else None
    if source is None:
        return None

    def fail(what: str):
        raise UserError(f"{where}: extras.source.{what}")

    if not isinstance(source, dict) or not isinstance(source.get("grid"), dict):
        fail("grid: a mapping with nx, ny, cell_m and origin_m")
    g = source["grid"]
    nx, ny, cell = g.get("nx"), g.get("ny"), g.get("cell_m")
    if not all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in (nx, ny)) or nx * ny > MAX_SOURCE_CELLS:
        fail(f"grid: nx and ny whole numbers > 0, at most {MAX_SOURCE_CELLS} cells")
    origin = g.get("origin_m")
    if not (isinstance(cell, (int, float)) and not isinstance(cell, bool) and 0 < cell < 1e3 and np.isfinite(cell)) \
            or not (isinstance(origin, list) and len(origin) == 2 and _finite(origin)):
        fail("grid: cell_m a number of metres in (0, 1000), origin_m two finite numbers")
    turn = source.get("world_from_source")
    if not (isinstance(turn, list) and _finite(turn) and np.asarray(turn, dtype=float).shape == (4, 4)):
        fail("world_from_source: a 4x4 matrix of finite numbers")
    rot = np.asarray(turn, dtype=float)
    if not (np.allclose(rot[:3, :3] @ rot[:3, :3].T, np.eye(3), atol=1e-6) and np.allclose(rot[3], [0, 0, 0, 1])):
        fail("world_from_source: a rigid transform (orthonormal rotation, last row 0 0 0 1)")
    frames = source.get("frames")
    if not (isinstance(frames, dict) and all(isinstance(v, int) and not isinstance(v, bool) and v >= 0
                                             for v in frames.values())):
        fail("frames: a mapping of scenario names to frame numbers >= 0")
    return {**source, "grid": {"nx": nx, "ny": ny, "cell_m": float(cell), "origin_m": [float(v) for v in origin]}}


def _finite(values) -> bool:
    """Whether ``values`` (nested lists) are all finite numbers."""
    try:
        return bool(np.all(np.isfinite(np.asarray(values, dtype=np.float64))))
    except (TypeError, ValueError):
        return False


def _write_frames(ds: Dataset, rig: Rig, names: list[str], cameras: list[CameraInfo], maps: list, grid: GroundGrid,
                  world_from_source: np.ndarray, progress: bool) -> int:
    """Each frame as a scenario of ``ds`` (its people, each view's labels and image); returns the boxes written."""
    from tqdm import tqdm

    boxes = 0
    for name, frame in tqdm(list(zip(names, rig.frames)), desc=f"importing {rig.format.name}", unit="frame",
                            disable=not progress, file=sys.stderr):
        actors, labels = [], {c.name: [] for c in cameras}
        for person in frame.people:
            xy = (world_from_source[:2, :2] @ grid.world_of_xy(grid.xy_of_position([person.position_id]))[0])
            center = np.array([xy[0], xy[1], PERSON_HEIGHT_M / 2])
            size = np.array([2 * PERSON_RADIUS_M, 2 * PERSON_RADIUS_M, PERSON_HEIGHT_M])
            aid = person.person_id + 1  # instance ids start at 1
            actors.append(Actor(aid, f"person_{person.person_id}", "pedestrian", Box3D(center, size, 0.0),
                                extras={"personID": person.person_id, "positionID": person.position_id}))
            for v, box in person.views.items():
                cam = cameras[v]
                clipped = clip_box_to_image(box, cam.width, cam.height)
                if clipped is None:
                    continue
                labels[cam.name].append(Label2D(
                    aid, "pedestrian", clipped,
                    frustum_fraction(cam.K, cam.camera_to_world, center, size, 0.0, cam.width, cam.height, NEAR_M),
                    None, float(np.linalg.norm(center - cam.camera_to_world[:3, 3])), None, None, 3,
                    {"annotated_box": box.tolist()}))
                boxes += 1
        scn = Scenario(name, actors, cameras, [LightingVariant(VARIANT, "none")],
                       {"source_frame": frame.number, "source_annotation": frame.annotation.name})
        for cam, image, lens_map in zip(cameras, frame.images, maps):
            rgb = read_rgb(image)
            if lens_map is not None:
                rgb = cv2.remap(rgb, *lens_map, cv2.INTER_LINEAR)
            write_rgb(ds.layout.rgb(name, cam.name, VARIANT), rgb)
            ds.write_labels(ViewLabels(name, cam.name, cam.width, cam.height, THRESHOLDS, labels[cam.name]))
        ds.write_scenario(scn)  # last: a scenario that exists is complete
    return boxes
