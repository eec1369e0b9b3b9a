"""Wildtrack- and MultiviewX-format folders written in the formats' exact layout (intrinsics with cv2.FileStorage,
Wildtrack's plain-text extrinsics in centimetres, MultiviewX's FileStorage extrinsics in metres, annotation JSON with
-1 for "not in this view", boxes projected with cv2.projectPoints): the fixture the importers' tests share."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from dataset_spec.rig_formats import FORMATS, camera_name
from dataset_spec.rig_import import PERSON_HEIGHT_M, cylinder_points

W, H = 320, 180
K = np.array([[260.0, 0, 159.5], [0, 260.0, 89.5], [0, 0, 1]])


def look_at(eye, target, up) -> np.ndarray:
    """World-to-camera (4, 4), OpenCV axes (x right, y down, z forward), for a world whose up is ``up``."""
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
    return w2c


def write_fixture(root: Path, fmt_name: str, z_up: bool = True, frames=(0, 5, 10), cameras: int = 3,
                  dist=np.zeros(5), suffix: str = ".png") -> dict:
    """A folder in ``fmt_name``'s layout: ``cameras`` cameras around people standing on grid cells, lens
    distortion ``dist`` (OpenCV's coefficients, as the real MultiviewX has), frames as ``suffix`` files;
    returns what was written (rvecs, tvecs in the format's unit, the people's positions per frame)."""
    fmt = FORMATS[fmt_name]
    grid, unit = fmt.grid, fmt.metres_per_unit
    s = 1.0 if z_up else -1.0  # the world's up is s * z
    centre = np.array([4.0, 6.0])  # metres, inside both grids
    rvecs, tvecs, w2cs = [], [], []
    for k in range(cameras):
        a = 2 * np.pi * k / cameras + 0.3
        eye = np.array([centre[0] + 9 * np.cos(a), centre[1] + 9 * np.sin(a), s * 4.0])
        w2c = look_at(eye, [*centre, 0.0], [0, 0, s])
        rvecs.append(cv2.Rodrigues(w2c[:3, :3])[0].reshape(3))
        tvecs.append(w2c[:3, 3] / unit)
        w2cs.append(w2c)
    calib = root / "calibrations"
    (calib / fmt.intrinsic_dir).mkdir(parents=True)
    (calib / "extrinsic").mkdir()
    for k in range(cameras):
        name = camera_name(fmt, k)
        fs = cv2.FileStorage(str(calib / fmt.intrinsic_dir / f"intr_{name}.xml"), cv2.FILE_STORAGE_WRITE)
        fs.write("camera_matrix", K)
        fs.write("distortion_coefficients", np.asarray(dist, np.float64).reshape(1, -1))
        fs.release()
        extr = calib / "extrinsic" / f"extr_{name}.xml"
        if fmt.plain_text_extrinsics:  # as Wildtrack ships them: not FileStorage
            extr.write_text(f'<?xml version="1.0"?>\n<opencv_storage>\n<rvec>{" ".join(map(str, rvecs[k]))}</rvec>\n'
                            f'<tvec>{" ".join(map(str, tvecs[k]))}</tvec>\n</opencv_storage>\n')
        else:
            fs = cv2.FileStorage(str(extr), cv2.FILE_STORAGE_WRITE)
            fs.write("rvec", rvecs[k].reshape(3, 1))
            fs.write("tvec", tvecs[k].reshape(3, 1))
            fs.release()
    (root / "annotations_positions").mkdir()
    people = {}
    rng = np.random.default_rng(7)
    for f, number in enumerate(frames):
        cells = grid.xy_of_world(centre + rng.uniform(-2.5, 2.5, size=(4, 2)))
        positions = grid.position_of_xy(cells)
        people[number] = positions
        entries = []
        for pid, pos in enumerate(positions):
            ground = grid.world_of_xy(grid.xy_of_position([pos]))
            pts = cylinder_points(ground, s * PERSON_HEIGHT_M)[0] / unit  # the format's world unit
            views = []
            for k in range(cameras):
                uv = cv2.projectPoints(pts, rvecs[k], tvecs[k], K, np.asarray(dist, np.float64))[0].reshape(-1, 2)
                box = [float(uv[:, 0].min()), float(uv[:, 1].min()), float(uv[:, 0].max()), float(uv[:, 1].max())]
                inside = box[2] > 0 and box[0] < W - 1 and box[3] > 0 and box[1] < H - 1
                views.append({"viewNum": k, **dict(zip(("xmin", "ymin", "xmax", "ymax"), box if inside else [-1] * 4))})
            entries.append({"personID": pid + 10 * f, "positionID": int(pos), "views": views})
        (root / "annotations_positions" / f"{number:0{fmt.annotation_digits}d}.json").write_text(json.dumps(entries))
        for k in range(cameras):
            img = np.full((H, W, 3), 90, np.uint8)
            for e in entries:
                v = e["views"][k]
                if v["xmin"] != -1:
                    cv2.rectangle(img, (int(v["xmin"]), int(v["ymin"])), (int(v["xmax"]), int(v["ymax"])), (200, 60, 40), -1)
            d = root / "Image_subsets" / f"C{k + 1}"
            d.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(d / f"{number:0{fmt.image_digits}d}{suffix}"), img)
    return {"rvecs": rvecs, "tvecs": tvecs, "people": people, "fmt": fmt}
