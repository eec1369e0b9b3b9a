"""Camera math in the spec's one convention (numpy only).

Convention (see SPEC.md, "Cameras"):

* World: metres, right-handed, +Z up (Blender's world).
* Camera axes: OpenCV. +x right, +y down, +z forward (the viewing direction).
* ``camera_to_world``: 4x4 rigid transform taking camera-axis points to world points.
* ``K``: 3x3 pinhole intrinsics in pixels. Pixel (u, v) has its centre at the continuous
  image coordinate (u, v); the image spans [-0.5, W-0.5] x [-0.5, H-0.5].
* Depth is planar: the camera-space z of the surface point, not the distance along the ray.

Usage::

    uv, z = project_points(K, camera_to_world, points_world)   # (N, 2), (N,)
    origins, dirs = pixel_rays(K, camera_to_world, uv)         # unit directions, world
"""
from __future__ import annotations

import numpy as np

# Blender camera axes (x right, y up, looking down -z) <-> OpenCV axes (x right, y down, +z forward).
BLENDER_TO_OPENCV_AXES = np.diag([1.0, -1.0, -1.0, 1.0])


def blender_to_opencv_camera_to_world(c2w_blender: np.ndarray) -> np.ndarray:
    """Convert a camera-to-world matrix with Blender camera axes to OpenCV axes.

    The flip is its own inverse, so this also converts back.
    """
    return np.asarray(c2w_blender, dtype=np.float64) @ BLENDER_TO_OPENCV_AXES


opencv_to_blender_camera_to_world = blender_to_opencv_camera_to_world


def invert_rigid(transform: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform (rotation + translation)."""
    transform = np.asarray(transform, dtype=np.float64)
    rot = transform[:3, :3]
    out = np.eye(4)
    out[:3, :3] = rot.T
    out[:3, 3] = -rot.T @ transform[:3, 3]
    return out


def world_to_camera(camera_to_world: np.ndarray) -> np.ndarray:
    """The 4x4 extrinsic matrix (world -> OpenCV camera axes)."""
    return invert_rigid(camera_to_world)


def transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points of shape (..., 3)."""
    points = np.asarray(points, dtype=np.float64)
    return points @ transform[:3, :3].T + transform[:3, 3]


def points_to_camera(camera_to_world: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    """World points (..., 3) -> camera-space points (..., 3), OpenCV axes."""
    return transform_points(world_to_camera(camera_to_world), points_world)


def project_camera_points(K: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
    """Pinhole projection of camera-space points (..., 3) to pixels (..., 2).

    Points with z <= 0 give meaningless (possibly infinite) pixels: check z yourself,
    or clip geometry at the near plane first (see ``boxes.clip_polygon_near``).
    """
    points_cam = np.asarray(points_cam, dtype=np.float64)
    z = points_cam[..., 2:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = points_cam[..., :2] / z
    return xy @ np.asarray(K)[:2, :2].T + np.asarray(K)[:2, 2]


def project_points(K: np.ndarray, camera_to_world: np.ndarray, points_world: np.ndarray):
    """World points (..., 3) -> (pixels (..., 2), planar depth z (...,)).

    ``z <= 0`` means the point is behind the camera; its pixel is not meaningful.
    """
    cam = points_to_camera(camera_to_world, points_world)
    return project_camera_points(K, cam), cam[..., 2]


def pixel_directions_camera(K: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Camera-space directions with z = 1 through pixels ``uv`` (..., 2)."""
    uv = np.asarray(uv, dtype=np.float64)
    homo = np.concatenate([uv, np.ones(uv.shape[:-1] + (1,))], axis=-1)
    return homo @ np.linalg.inv(np.asarray(K, dtype=np.float64)).T


def pixel_rays(K: np.ndarray, camera_to_world: np.ndarray, uv: np.ndarray):
    """World-space rays through pixels ``uv`` (..., 2).

    Returns ``(origins (..., 3), unit directions (..., 3))``. A point at distance t along
    the ray has planar depth ``t * dirs_cam_z`` where ``dirs_cam_z`` is the camera-space z
    of the unit direction.
    """
    c2w = np.asarray(camera_to_world, dtype=np.float64)
    dirs_cam = pixel_directions_camera(K, uv)
    dirs_cam /= np.linalg.norm(dirs_cam, axis=-1, keepdims=True)
    dirs = dirs_cam @ c2w[:3, :3].T
    origins = np.broadcast_to(c2w[:3, 3], dirs.shape).copy()
    return origins, dirs


def unproject_depth(K: np.ndarray, camera_to_world: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Planar depth map (H, W) -> world points (H, W, 3). Pixels with depth 0 give NaN."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    dirs = pixel_directions_camera(K, np.stack([u, v], axis=-1))
    pts_cam = dirs * depth[..., None]
    pts_cam[depth <= 0] = np.nan
    return transform_points(np.asarray(camera_to_world, dtype=np.float64), pts_cam)


def intrinsics_from_blender(
    *,
    lens_mm: float,
    sensor_width_mm: float,
    sensor_height_mm: float,
    sensor_fit: str,
    shift_x: float,
    shift_y: float,
    width: int,
    height: int,
    pixel_aspect: float = 1.0,
) -> np.ndarray:
    """K (3x3, pixels, integer pixel centres) from Blender camera settings.

    ``pixel_aspect`` is ``render.pixel_aspect_y / render.pixel_aspect_x``. ``sensor_fit``
    is Blender's ``'AUTO' | 'HORIZONTAL' | 'VERTICAL'``. Matches
    ``bpy_extras.object_utils.world_to_camera_view`` (tested in blender tests).
    """
    if sensor_fit == "AUTO":
        fit = "HORIZONTAL" if width >= pixel_aspect * height else "VERTICAL"
        sensor_mm = sensor_width_mm
    elif sensor_fit == "HORIZONTAL":
        fit, sensor_mm = "HORIZONTAL", sensor_width_mm
    elif sensor_fit == "VERTICAL":
        fit, sensor_mm = "VERTICAL", sensor_height_mm
    else:
        raise ValueError(f"unknown sensor_fit {sensor_fit!r}")
    view_fac = width if fit == "HORIZONTAL" else pixel_aspect * height
    fx = lens_mm / sensor_mm * view_fac
    fy = fx / pixel_aspect
    cx = (width - 1) / 2.0 - shift_x * view_fac
    cy = (height - 1) / 2.0 + shift_y * view_fac / pixel_aspect
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """K for an image resized by (sx, sy), keeping the integer-pixel-centre convention."""
    K = np.array(K, dtype=np.float64)
    out = K.copy()
    out[0, 0] *= sx
    out[1, 1] *= sy
    out[0, 1] *= sx
    out[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    out[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return out


def translate_intrinsics(K: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """K for an image whose content is moved by (dx, dy) pixels (pixel u -> u + dx, v -> v + dy):
    the principal point moves with it; the camera pose is unchanged."""
    out = np.array(K, dtype=np.float64)
    out[0, 2] += dx
    out[1, 2] += dy
    return out


# Reflection of the world in the plane x = 0 (and of camera axes in their own x = 0 plane).
MIRROR_X = np.diag([-1.0, 1.0, 1.0, 1.0])


def mirror_camera(K: np.ndarray, camera_to_world: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The camera that sees the world mirrored in the plane x = 0 as this camera's image flipped
    left-right (pixel u -> width - 1 - u, v unchanged, same depth).

    With M = diag(-1, 1, 1) the mirrored world point is M X; the new camera_to_world is
    M @ c2w @ M (a proper rigid transform again: the two reflections cancel in the rotation's
    determinant) and the principal point moves to cx' = width - 1 - cx (skew changes sign).
    Used for consistent multi-view flip augmentation: flip every view's image and replace every
    camera by its mirror; ground height (z) is unchanged.
    """
    K2 = np.array(K, dtype=np.float64)
    K2[0, 1] = -K2[0, 1]
    K2[0, 2] = width - 1 - K2[0, 2]
    return K2, MIRROR_X @ np.asarray(camera_to_world, dtype=np.float64) @ MIRROR_X


def check_intrinsics(K) -> str | None:
    """Return a problem description, or None when K is a valid pinhole matrix."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        return f"K must be 3x3, got shape {K.shape}"
    if not np.all(np.isfinite(K)):
        return "K has non-finite entries"
    if abs(K[1, 0]) > 1e-9 or abs(K[2, 0]) > 1e-9 or abs(K[2, 1]) > 1e-9:
        return "K is not upper-triangular"
    if abs(K[2, 2] - 1.0) > 1e-9:
        return f"K[2,2] must be 1, got {K[2, 2]}"
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        return "K has non-positive focal lengths"
    return None


def check_rigid(transform, tol: float = 1e-5) -> str | None:
    """Return a problem description, or None when ``transform`` is a 4x4 rigid transform."""
    T = np.asarray(transform, dtype=np.float64)
    if T.shape != (4, 4):
        return f"transform must be 4x4, got shape {T.shape}"
    if not np.all(np.isfinite(T)):
        return "transform has non-finite entries"
    if not np.allclose(T[3], [0, 0, 0, 1], atol=tol):
        return "last row of the transform must be [0, 0, 0, 1]"
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=tol):
        return "rotation part is not orthonormal"
    if np.linalg.det(R) < 0:
        return "rotation part is a reflection (det < 0)"
    return None
