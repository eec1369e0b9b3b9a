"""The files of the field's multi-camera pedestrian datasets (Wildtrack, MultiviewX), read and written
in their own layout and units; facts in ../shared/reference/FACTS.md, "Real multi-view pedestrian
datasets"::

    fmt = FORMATS["wildtrack"]
    rig = read_rig(fmt, "Wildtrack")          # cameras in this project's convention, frames, people
    rig.cameras[0].K, rig.frames[0].people[0].views   # {view index: annotated box}

    write_intrinsics(path, K)                  # OpenCV FileStorage XML, as both datasets ship it
    write_extrinsics(path, rvec, tvec, fmt)    # FileStorage (MultiviewX) or plain text (Wildtrack)

A folder holds ``Image_subsets/C1..CN/<frame>.png``, ``annotations_positions/<frame>.json`` and
``calibrations/<intrinsic dir>/intr_<camera>.xml`` + ``calibrations/extrinsic/extr_<camera>.xml``;
camera ``Ck`` is the k-th name of the format's calibration list and ``viewNum`` k-1. Extrinsics map
world to camera (``x_cam = R(rvec) X + t``, OpenCV axes) in the format's world unit; a camera here is
camera-to-world in metres. Every problem is a one-line ``UserError`` naming the file.
"""
from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .atomic import atomic_path, atomic_write_text
from .camera import invert_rigid
from .dataset import read_json
from .cli_support import UserError
from .errors import SpecError
from .ground_grid import GRIDS, GroundGrid
from .images import image_size


@dataclass(frozen=True)
class RigFormat:
    name: str
    camera_names: tuple[str, ...] | None  # calibration stems of C1, C2, ... (None: Camera1, Camera2, ... unbounded)
    intrinsic_dir: str  # under calibrations/
    metres_per_unit: float  # the world unit of the extrinsics and of the grid's origin
    plain_text_extrinsics: bool  # Wildtrack: <rvec>a b c</rvec>; MultiviewX: FileStorage matrices
    image_digits: int  # image file names: the frame number, zero-padded
    annotation_digits: int
    grid: GroundGrid


FORMATS = {
    "wildtrack": RigFormat("wildtrack", ("CVLab1", "CVLab2", "CVLab3", "CVLab4", "IDIAP1", "IDIAP2", "IDIAP3"),
                           "intrinsic_zero", 0.01, True, 8, 8, GRIDS["wildtrack"]),
    "multiviewx": RigFormat("multiviewx", None, "intrinsic", 1.0, False, 4, 5, GRIDS["multiviewx"]),
}


def camera_name(fmt: RigFormat, k: int) -> str:
    """The calibration file stem of camera folder ``C{k + 1}``."""
    return fmt.camera_names[k] if fmt.camera_names else f"Camera{k + 1}"


@dataclass
class RigCamera:
    name: str
    width: int
    height: int
    K: np.ndarray  # (3, 3)
    camera_to_world: np.ndarray  # (4, 4) metres, OpenCV camera axes
    rvec: np.ndarray  # (3,) as the file gives it
    tvec: np.ndarray  # (3,) in the format's unit
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(0))  # OpenCV's coefficients (empty: none)


@dataclass
class Person:
    person_id: int
    position_id: int
    views: dict[int, np.ndarray]  # view index -> annotated [xmin, ymin, xmax, ymax] (as given: may leave the image)


@dataclass
class Frame:
    number: int
    images: list[Path]  # one per camera
    people: list[Person] = field(default_factory=list)
    annotation: Path | None = None


@dataclass
class Rig:
    format: RigFormat
    root: Path
    cameras: list[RigCamera]
    frames: list[Frame]


# ------------------------------------------------------------------------------------ calibration
def _matrix_text(path: Path, tag: str) -> np.ndarray:
    """The numbers of ``<tag>`` in an OpenCV XML file: a FileStorage matrix (its ``<data>``) or plain text."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise UserError(f"{path}: not readable XML ({exc})") from None
    node = root.find(tag)
    if node is None:
        raise UserError(f"{path}: no <{tag}> in the file")
    data = node.find("data")
    text = (data.text if data is not None else node.text) or ""
    try:
        return np.array([float(v) for v in text.split()], dtype=np.float64)
    except ValueError:
        raise UserError(f"{path}: <{tag}> holds something other than numbers") from None


def read_intrinsics(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3), distortion coefficients (OpenCV's order; empty when the file has none)) from an ``intr_*.xml``.
    The real MultiviewX holds small non-zero coefficients, which MVDet ignores (``rig_import``: the user's choice)."""
    if not path.is_file():
        raise UserError(f"{path}: intrinsics file is missing")
    K = _matrix_text(path, "camera_matrix")
    if K.size != 9:
        raise UserError(f"{path}: camera_matrix has {K.size} numbers, not 9")
    K = K.reshape(3, 3)
    if not (np.isfinite(K).all() and K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1])
            and K[1, 0] == K[2, 0] == K[2, 1] == 0):
        raise UserError(f"{path}: camera_matrix is not a pinhole intrinsic matrix")
    try:
        dist = _matrix_text(path, "distortion_coefficients")
    except UserError:
        dist = np.zeros(0)
    if dist.size not in (0, 4, 5, 8, 12, 14) or not np.isfinite(dist).all():
        raise UserError(f"{path}: distortion_coefficients must be 4, 5, 8, 12 or 14 finite numbers, got {dist.size}")
    return K, dist


def read_extrinsics(path: Path, fmt: RigFormat) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rvec, tvec as in the file, camera_to_world (4, 4) in metres) from an ``extr_*.xml``."""
    if not path.is_file():
        raise UserError(f"{path}: extrinsics file is missing")
    rvec, tvec = _matrix_text(path, "rvec"), _matrix_text(path, "tvec")
    if rvec.size != 3 or tvec.size != 3:
        raise UserError(f"{path}: rvec and tvec need 3 numbers each")
    world_to_camera = np.eye(4)
    world_to_camera[:3, :3] = cv2.Rodrigues(rvec.reshape(3, 1))[0]
    world_to_camera[:3, 3] = tvec * fmt.metres_per_unit
    return rvec, tvec, invert_rigid(world_to_camera)


def write_intrinsics(path: Path, K: np.ndarray) -> None:
    """``camera_matrix`` and zero ``distortion_coefficients`` with cv2.FileStorage, atomically."""
    with atomic_path(path) as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_XML)
        fs.write("camera_matrix", np.asarray(K, dtype=np.float64))
        fs.write("distortion_coefficients", np.zeros((1, 5)))
        fs.release()


def write_extrinsics(path: Path, rvec: np.ndarray, tvec: np.ndarray, fmt: RigFormat) -> None:
    """rvec, tvec (the format's unit) as the format stores them: plain text (Wildtrack) or FileStorage."""
    rvec, tvec = np.asarray(rvec, np.float64).reshape(3), np.asarray(tvec, np.float64).reshape(3)
    if fmt.plain_text_extrinsics:
        text = ('<?xml version="1.0"?>\n<opencv_storage>\n<rvec>' + " ".join(f"{v:.12g}" for v in rvec)
                + "</rvec>\n<tvec>" + " ".join(f"{v:.12g}" for v in tvec) + "</tvec>\n</opencv_storage>\n")
        atomic_write_text(path, text)
        return
    with atomic_path(path) as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_XML)
        fs.write("rvec", rvec.reshape(3, 1))
        fs.write("tvec", tvec.reshape(3, 1))
        fs.release()


def extrinsics_of(camera_to_world: np.ndarray, fmt: RigFormat) -> tuple[np.ndarray, np.ndarray]:
    """(rvec, tvec in the format's unit) of a camera-to-world transform in metres."""
    w2c = invert_rigid(np.asarray(camera_to_world, dtype=np.float64))
    return cv2.Rodrigues(w2c[:3, :3])[0].reshape(3), w2c[:3, 3] / fmt.metres_per_unit


# ------------------------------------------------------------------------------------ annotations
def read_annotation(path: Path, grid: GroundGrid, num_views: int) -> list[Person]:
    """The people of one ``annotations_positions`` JSON; boxes of -1 (not in that view) left out."""
    try:
        raw = read_json(path, "annotations_positions")
    except SpecError as exc:
        raise UserError(str(exc)) from None
    if not isinstance(raw, list):
        raise UserError(f"{path}: expected a list of people")
    people = []
    for k, entry in enumerate(raw):
        try:
            pid, pos = int(entry["personID"]), int(entry["positionID"])
            views = {}
            for v in entry["views"]:
                box = np.array([v["xmin"], v["ymin"], v["xmax"], v["ymax"]], dtype=np.float64)
                num = int(v["viewNum"])
                if np.all(box == -1):
                    continue
                if not 0 <= num < num_views:
                    raise UserError(f"{path}: person {k}: viewNum {num} but the rig has {num_views} cameras")
                if box[2] < box[0] or box[3] < box[1]:
                    raise UserError(f"{path}: person {pid}, view {num}: xmax < xmin or ymax < ymin")
                views[num] = box
        except (KeyError, TypeError, ValueError):
            raise UserError(f"{path}: person {k}: needs personID, positionID and views of viewNum, xmin, ymin, "
                            "xmax, ymax") from None
        if not 0 <= pos < grid.nx * grid.ny:
            raise UserError(f"{path}: person {pid}: positionID {pos} is outside the {grid.nx} x {grid.ny} ground grid")
        if any(p.person_id == pid for p in people):
            raise UserError(f"{path}: personID {pid} appears twice")
        if not 0 <= pid < 65535:
            raise UserError(f"{path}: personID {pid} outside 0..65534")
        people.append(Person(pid, pos, views))
    return people


def write_annotation(path: Path, people: list[dict]) -> None:
    """One frame's ``annotations_positions`` JSON (entries as the datasets spell them)."""
    atomic_write_text(path, json.dumps(people, indent=1))


# ------------------------------------------------------------------------------------ a whole folder
def read_rig(fmt: RigFormat, root: str | Path, grid: GroundGrid | None = None) -> Rig:
    """Cameras, frames and people of a folder in ``fmt``'s layout, every file checked (names, sizes,
    calibration, positions inside ``grid``, by default the format's) before anything is returned."""
    root = Path(root)
    grid = grid or fmt.grid
    if not root.is_dir():
        raise UserError(f"{root}: no such folder")
    subsets, ann_dir, calib = root / "Image_subsets", root / "annotations_positions", root / "calibrations"
    for need in (subsets, ann_dir, calib):
        if not need.is_dir():
            raise UserError(f"{need}: folder is missing (a {fmt.name} folder has Image_subsets, annotations_positions "
                            "and calibrations)")
    cam_dirs = sorted((p for p in subsets.iterdir() if p.is_dir() and re.fullmatch(r"C\d+", p.name)),
                      key=lambda p: int(p.name[1:]))
    if not cam_dirs:
        raise UserError(f"{subsets}: no camera folders C1, C2, ...")
    numbers = [int(p.name[1:]) for p in cam_dirs]
    most = len(fmt.camera_names) if fmt.camera_names else len(cam_dirs)
    if numbers != list(range(1, len(cam_dirs) + 1)) or len(cam_dirs) > most:
        raise UserError(f"{subsets}: camera folders must be C1..CN with N <= {most}, got "
                        f"{', '.join(p.name for p in cam_dirs)}")
    annotations = sorted(p for p in ann_dir.glob("*.json") if p.stem.isdigit())
    if not annotations:
        raise UserError(f"{ann_dir}: no annotation files (<frame>.json)")
    frames, sizes = [], [None] * len(cam_dirs)
    for ann in annotations:
        number = int(ann.stem)
        images = [frame_image(d, number, fmt.image_digits) for d in cam_dirs]
        for k, img in enumerate(images):
            try:
                hw = image_size(img)
            except SpecError as exc:
                raise UserError(f"{img}: {exc.message} (frame {number} of {ann})") from None
            if sizes[k] is None:
                sizes[k] = hw
            elif hw != sizes[k]:
                raise UserError(f"{img}: {hw[1]}x{hw[0]}, but camera C{k + 1}'s other images are "
                                f"{sizes[k][1]}x{sizes[k][0]}")
        frames.append(Frame(number, images, read_annotation(ann, grid, len(cam_dirs)), ann))
    if len(set(sizes)) > 1:
        k = next(k for k, hw in enumerate(sizes) if hw != sizes[0])
        raise UserError(f"{cam_dirs[k]}: its images are {sizes[k][1]}x{sizes[k][0]}, camera C1's "
                        f"{sizes[0][1]}x{sizes[0][0]}: every camera of a rig needs the same image size")
    cameras = []
    for k, (h, w) in enumerate(sizes):
        name = camera_name(fmt, k)
        intr = calib / fmt.intrinsic_dir / f"intr_{name}.xml"
        K, dist = read_intrinsics(intr)
        check_principal_point(intr, K, w, h)
        rvec, tvec, c2w = read_extrinsics(calib / "extrinsic" / f"extr_{name}.xml", fmt)
        cameras.append(RigCamera(name, w, h, K, c2w, rvec, tvec, dist))
    return Rig(fmt, root, cameras, frames)


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def frame_image(folder: Path, number: int, digits: int) -> Path:
    """A camera folder's image of frame ``number``: ``<number>.png`` or ``.jpg`` (both datasets ship either)."""
    stem = f"{number:0{digits}d}"
    for suffix in IMAGE_SUFFIXES:
        if (folder / f"{stem}{suffix}").is_file():
            return folder / f"{stem}{suffix}"
    return folder / f"{stem}.png"  # missing: the size check names it


def check_principal_point(path: Path, K: np.ndarray, width: int, height: int) -> None:
    """One line when the calibration's principal point is not in the middle half of the camera's images:
    images of another size than the calibration's (resized frames put it at an edge)."""
    cx, cy = K[0, 2], K[1, 2]
    if not (0.25 * width <= cx <= 0.75 * width and 0.25 * height <= cy <= 0.75 * height):
        raise UserError(f"{path}: its principal point ({cx:.0f}, {cy:.0f}) does not fit the camera's {width}x{height} "
                        f"images (the calibration suggests about {2 * cx + 1:.0f}x{2 * cy + 1:.0f}): are the images "
                        "resized?")
