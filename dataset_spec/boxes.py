"""Box geometry in numpy: oriented 3D boxes and axis-aligned 2D boxes.

3D boxes (see SPEC.md, "Actors"): ``center`` (3,) world metres at the box's middle,
``size`` (length, width, height) along the actor's local (x forward, y left, z up) axes,
``yaw`` radians about world +Z from world +X to the actor's forward axis.
Corner order (local coordinates as multiples of half the size)::

    0 (+,+,-) 1 (-,+,-) 2 (-,-,-) 3 (+,-,-)     bottom face, counter-clockwise from above
    4 (+,+,+) 5 (-,+,+) 6 (-,-,+) 7 (+,-,+)     top face, same order

2D boxes are ``[x0, y0, x1, y1]`` in the spec's continuous pixel coordinates (pixel (u, v)
has its centre at (u, v); the image spans [-0.5, W-0.5] x [-0.5, H-0.5]).
"""
from __future__ import annotations

import numpy as np

from .camera import points_to_camera, project_camera_points

_CORNER_SIGNS = np.array(
    [[1, 1, -1], [-1, 1, -1], [-1, -1, -1], [1, -1, -1],
     [1, 1, 1], [-1, 1, 1], [-1, -1, 1], [1, -1, 1]], dtype=np.float64)

# The 12 edges of the box as corner index pairs.
BOX_EDGES = np.array(
    [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
     [0, 4], [1, 5], [2, 6], [3, 7]])


def yaw_rotation(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def box_corners(center, size, yaw: float) -> np.ndarray:
    """The 8 world corners (8, 3) of an oriented box, in the documented order."""
    local = _CORNER_SIGNS * (np.asarray(size, dtype=np.float64) / 2.0)
    return local @ yaw_rotation(yaw).T + np.asarray(center, dtype=np.float64)


def box_from_corners(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Recover (center, size, yaw) from 8 corners in the documented order."""
    c = np.asarray(corners, dtype=np.float64)
    center = c.mean(axis=0)
    length = np.linalg.norm(c[0] - c[1])
    width = np.linalg.norm(c[0] - c[3])
    height = np.linalg.norm(c[0] - c[4])
    fwd = c[0] - c[1]
    yaw = float(np.arctan2(fwd[1], fwd[0]))
    return center, np.array([length, width, height]), yaw


def corners_match_box(corners, center, size, yaw: float, tol: float = 1e-3) -> bool:
    return bool(np.allclose(np.asarray(corners), box_corners(center, size, yaw), atol=tol))


def points_in_box(points: np.ndarray, center, size, yaw: float, margin: float = 0.0) -> np.ndarray:
    """Boolean mask (N,) of points (N, 3) inside the oriented box (grown by ``margin``)."""
    local = (np.asarray(points, dtype=np.float64) - np.asarray(center)) @ yaw_rotation(yaw)
    return np.all(np.abs(local) <= np.asarray(size) / 2.0 + margin, axis=-1)


def box_grid_points(center, size, yaw: float, samples: int) -> np.ndarray:
    """World points (samples**3, 3) at the centres of a regular samples^3 grid of cells filling the box."""
    t = (np.arange(samples) + 0.5) / samples - 0.5
    local = np.stack(np.meshgrid(t, t, t, indexing="ij"), axis=-1).reshape(-1, 3) * np.asarray(size, dtype=np.float64)
    return local @ yaw_rotation(yaw).T + np.asarray(center, dtype=np.float64)


def in_view(K, camera_to_world, points_world: np.ndarray, width: int, height: int, near: float) -> np.ndarray:
    """(N,) bool: the points lie in the view frustum (planar depth >= ``near``, projected into the image)."""
    cam = points_to_camera(camera_to_world, points_world)
    front = cam[:, 2] >= near
    uv = project_camera_points(K, np.where(front[:, None], cam, [0.0, 0.0, 1.0]))
    return front & (uv[:, 0] >= -0.5) & (uv[:, 0] <= width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= height - 0.5)


def frustum_fraction(K, camera_to_world, center, size, yaw: float, width: int, height: int, near: float,
                     samples: int = 24) -> float:
    """The share of an oriented 3D box's volume inside a camera's view frustum, in [0, 1].

    Exactly 1 when all 8 corners are in view (both shapes are convex), else measured on a
    ``samples``^3 grid of cell centres (error of the order of one cell, 1/samples of the box).
    It is what "how much of the road user is in frame" means for a road user beside the camera
    too, where an image-plane silhouette grows without bound as the box crosses the near plane.
    """
    if in_view(K, camera_to_world, box_corners(center, size, yaw), width, height, near).all():
        return 1.0
    return float(in_view(K, camera_to_world, box_grid_points(center, size, yaw, samples), width, height, near).mean())


def clip_segments_near(p0: np.ndarray, p1: np.ndarray, near: float):
    """Clip camera-space segments (N, 3)-(N, 3) to ``z >= near``.

    Returns the clipped endpoints and a mask of segments that keep any part.
    """
    z0, z1 = p0[:, 2], p1[:, 2]
    keep = (z0 >= near) | (z1 >= near)
    denom = np.where(np.abs(z1 - z0) < 1e-12, 1.0, z1 - z0)
    t = np.clip((near - z0) / denom, 0.0, 1.0)[:, None]
    crossing = p0 + t * (p1 - p0)
    q0 = np.where((z0 >= near)[:, None], p0, crossing)
    q1 = np.where((z1 >= near)[:, None], p1, crossing)
    return q0, q1, keep


def project_box_2d(K, camera_to_world, corners_world, near: float = 0.05):
    """Amodal 2D box of a 3D box: clipped at the near plane, projected, not image-clipped.

    Returns ``[x0, y0, x1, y1]`` or None when the box lies entirely behind ``near``.
    Projecting the near-clipped edges (rather than raw corners) means corners behind the
    camera never produce wrapped boxes.
    """
    cam = points_to_camera(camera_to_world, corners_world)
    q0, q1, keep = clip_segments_near(cam[BOX_EDGES[:, 0]], cam[BOX_EDGES[:, 1]], near)
    if not keep.any():
        return None
    pts = np.concatenate([q0[keep], q1[keep]])
    uv = project_camera_points(K, pts)
    return np.array([uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()])


def clip_box_to_image(box, width: int, height: int):
    """Clip ``[x0, y0, x1, y1]`` to the image extent; None when nothing is left."""
    x0, y0, x1, y1 = box
    x0, x1 = max(x0, -0.5), min(x1, width - 0.5)
    y0, y1 = max(y0, -0.5), min(y1, height - 0.5)
    if x1 <= x0 or y1 <= y0:
        return None
    return np.array([x0, y0, x1, y1], dtype=np.float64)


def box_in_view(K, camera_to_world, width: int, height: int, near: float, far: float, center, size,
                yaw: float) -> tuple[np.ndarray, float] | None:
    """A 3D box as a camera's 2D labels see it: the one rule for labelled road users (``tools.projection``)
    and for 3D detections put into views (``pnyolo.decoding.world``). None when every corner lies beyond
    ``far``, or nothing of it in front of ``near`` falls inside the image; otherwise its box clipped at
    the near plane, projected and clipped to the image ``[x0, y0, x1, y1]`` and its centre's distance
    from the camera (metres). Its in-frame fraction is ``frustum_fraction`` at ``max(near, 1e-4)``."""
    near = max(near, 1e-4)
    corners = box_corners(center, size, yaw)
    if points_to_camera(camera_to_world, corners)[:, 2].min() > far:
        return None
    box = project_box_2d(K, camera_to_world, corners, near=near)
    box = None if box is None else clip_box_to_image(box, width, height)
    if box is None:
        return None
    return box, float(np.linalg.norm(np.asarray(center, dtype=np.float64) - np.asarray(camera_to_world)[:3, 3]))


def flip_box_x(box, width: int) -> np.ndarray:
    """``[x0, y0, x1, y1]`` in an image flipped left-right (pixel u -> width - 1 - u)."""
    x0, y0, x1, y1 = np.asarray(box, dtype=np.float64)
    return np.array([width - 1 - x1, y0, width - 1 - x0, y1])


def box_to_yolo(box, width: int, height: int) -> np.ndarray:
    """``[x0, y0, x1, y1]`` pixels -> YOLO ``[cx, cy, w, h]`` as fractions of the image."""
    x0, y0, x1, y1 = np.asarray(box, dtype=np.float64)
    return np.array([((x0 + x1) / 2 + 0.5) / width, ((y0 + y1) / 2 + 0.5) / height,
                     (x1 - x0) / width, (y1 - y0) / height])


def yolo_to_box(yolo, width: int, height: int) -> np.ndarray:
    """Inverse of ``box_to_yolo``."""
    cx, cy, w, h = np.asarray(yolo, dtype=np.float64)
    cx, cy = cx * width - 0.5, cy * height - 0.5
    return np.array([cx - w * width / 2, cy - h * height / 2, cx + w * width / 2, cy + h * height / 2])


def box_area(boxes: np.ndarray) -> np.ndarray:
    boxes = np.asarray(boxes, dtype=np.float64)
    return np.clip(boxes[..., 2] - boxes[..., 0], 0, None) * np.clip(boxes[..., 3] - boxes[..., 1], 0, None)


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise IoU of boxes a (N, 4) and b (M, 4) -> (N, M)."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0, None), axis=-1)
    union = box_area(a)[:, None] + box_area(b)[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1), 0.0)


def boxes_overlap(a_center, a_size, a_yaw: float, b_center, b_size, b_yaw: float, margin: float = 0.0) -> bool:
    """Whether two upright boxes (centre, size (length, width, height), yaw) overlap by more than ``margin`` metres:
    their heights' intervals and their ground footprints (separating axes of the two rectangles)."""
    if abs(float(a_center[2]) - float(b_center[2])) >= (float(a_size[2]) + float(b_size[2])) / 2 - margin:
        return False
    quads = [box_corners(c, s, y)[:4, :2] for c, s, y in ((a_center, a_size, a_yaw), (b_center, b_size, b_yaw))]
    for quad in quads:
        for k in range(4):
            edge = quad[(k + 1) % 4] - quad[k]
            axis = np.array([-edge[1], edge[0]]) / max(float(np.hypot(*edge)), 1e-12)
            pa, pb = quads[0] @ axis, quads[1] @ axis
            if pa.max() - margin <= pb.min() or pb.max() - margin <= pa.min():
                return False
    return True
