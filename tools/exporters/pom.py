"""``rectangles.pom``: where a person standing on each ground-grid position appears in each camera, the file
the POM family of tools reads beside a MultiviewX- or Wildtrack-layout folder (GMVD's varying-camera
evaluation builds each camera set's coverage from it)::

    RECTANGLE <camera> <position> <xmin> <ymin> <xmax> <ymax>     the box of a person at that position
    RECTANGLE <camera> <position> notvisible                     not in that camera's image

Cameras from 0, positions as the annotations number them (``x + NX * y``). The person is MultiviewX's
cylinder (radius 0.16 m, height 1.8 m) standing on the cell's corner point; the box bounds its 8 extreme
points, its bottom the foot point, in whole pixels. A position is listed, for every camera, when some camera
sees it (its foot point in front of the camera and inside the image); the others are left out, which the
readers take as seen by none (a grid of millions of cells would otherwise take gigabytes).

    write_pom(path, cameras, grid)   # cameras: CameraInfo in the export's world
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from dataset_spec.atomic import atomic_path
from dataset_spec.camera import project_points
from dataset_spec.ground_grid import GroundGrid
from dataset_spec.rig_import import PERSON_HEIGHT_M, PERSON_RADIUS_M

CHUNK = 1 << 18  # positions projected at a time (memory bounded for any grid)


def _boxes(cam, ground: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P, 4) int boxes and (P,) visibility of people standing at ``ground`` (P, 2) in ``cam``."""
    r, h = PERSON_RADIUS_M, PERSON_HEIGHT_M
    corners = np.array([[dx, dy, z] for dx in (-r, r) for dy in (-r, r) for z in (0.0, h)])
    pts = np.concatenate([ground, np.zeros((len(ground), 1))], axis=1)[:, None, :] + corners[None]
    uv, depth = project_points(cam.K, cam.camera_to_world, pts)
    foot_uv, foot_z = project_points(cam.K, cam.camera_to_world, np.concatenate([ground, np.zeros((len(ground), 1))],
                                                                                 axis=1))
    seen = (foot_z > cam.near) & (depth > cam.near).all(axis=1) & (foot_uv[:, 0] >= -0.5) & \
        (foot_uv[:, 0] < cam.width - 0.5) & (foot_uv[:, 1] >= -0.5) & (foot_uv[:, 1] < cam.height - 0.5)
    boxes = np.stack([uv[..., 0].min(axis=1), uv[..., 1].min(axis=1), uv[..., 0].max(axis=1), foot_uv[:, 1]], axis=1)
    return np.rint(np.nan_to_num(boxes, posinf=0, neginf=0)).astype(np.int64), seen


def write_pom(path: str | Path, cameras: list, grid: GroundGrid) -> int:
    """Write ``rectangles.pom`` for ``cameras`` (in the grid's world) over every position of ``grid``; returns
    how many positions some camera sees."""
    listed = 0
    with atomic_path(path) as tmp, open(tmp, "w", encoding="ascii") as fh:
        for start in range(0, grid.nx * grid.ny, CHUNK):
            pos = np.arange(start, min(start + CHUNK, grid.nx * grid.ny))
            ground = grid.world_of_xy(grid.xy_of_position(pos))
            per_cam = [_boxes(cam, ground) for cam in cameras]
            any_seen = np.any([seen for _, seen in per_cam], axis=0)
            for k, (boxes, seen) in enumerate(per_cam):
                rows = []
                for p, b, s in zip(pos[any_seen], boxes[any_seen], seen[any_seen]):
                    rows.append(f"RECTANGLE {k} {p} {b[0]} {b[1]} {b[2]} {b[3]}\n" if s
                                else f"RECTANGLE {k} {p} notvisible\n")
                fh.write("".join(rows))
            listed += int(any_seen.sum())
    return listed


def read_pom(path: str | Path) -> dict[int, dict[int, tuple[int, int, int, int] | None]]:
    """{position: {camera: box or None (notvisible)}} of a ``rectangles.pom`` (as its readers parse it)."""
    out: dict[int, dict] = {}
    for line in Path(path).read_text(encoding="ascii").splitlines():
        parts = line.split()
        if len(parts) < 4 or parts[0] != "RECTANGLE":
            continue
        cam, pos = int(parts[1]), int(parts[2])
        out.setdefault(pos, {})[cam] = None if parts[3] == "notvisible" else tuple(int(v) for v in parts[3:7])
    return out
