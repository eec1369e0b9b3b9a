"""Camera math in torch, in the spec's one convention (see ``dataset_spec.camera``).

OpenCV camera axes (x right, y down, z forward), world metres with +Z up, ``camera_to_world``
4x4, pixel (u, v) centred at continuous (u, v) so the image spans [-0.5, W-0.5]. These are the
torch twins of the numpy functions in ``dataset_spec.camera`` and are tested against them.

Components (nerfstudio style: one job each)::

    uv = grid_cell_centres(grid_h, grid_w, width, height)               # (Sh, Sw, 2)
    origins, dirs = pixel_rays(K, c2w, uv)                               # unit dirs, world
    t, valid = sample_along_rays(origins, dirs, 16, 2.0, 42.0)           # (R, S), (R, S): ray_samplers
    points = origins[:, None] + t[..., None] * dirs[:, None]             # (R, S, 3)
    uv_v, z_v, ok = project_to_views(K_all, c2w_all, points, W, H)       # (V, ...,2), (V, ...), (V, ...)
    cams = Cameras(K_all, c2w_all, W, H)                                  # the same, V views as one object
    origins, dirs = cams.pixel_rays(uv)                                  # (V, ..., 3) each
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

# Points closer than this (planar depth, metres) to a camera are treated as behind it: their
# projection would be huge or infinite (the original code's second NaN source).
MIN_DEPTH = 1e-3


def invert_rigid(transform: Tensor) -> Tensor:
    """Inverse of rigid transforms (..., 4, 4)."""
    rot = transform[..., :3, :3]
    out = torch.zeros_like(transform)
    rt = rot.transpose(-1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -(rt @ transform[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def points_to_camera(camera_to_world: Tensor, points_world: Tensor) -> Tensor:
    """World points (..., 3) -> camera points (..., 3) for one camera (4, 4)."""
    w2c = invert_rigid(camera_to_world)
    return points_world @ w2c[:3, :3].T + w2c[:3, 3]


def project_camera_points(K: Tensor, points_cam: Tensor) -> Tensor:
    """Camera points (..., 3) -> pixels (..., 2). z <= 0 gives meaningless pixels; check z."""
    z = points_cam[..., 2:3]
    safe = torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
    xy = points_cam[..., :2] / safe
    return xy @ K[:2, :2].T + K[:2, 2]


def project_points(K: Tensor, camera_to_world: Tensor, points_world: Tensor) -> tuple[Tensor, Tensor]:
    """World points (..., 3) -> (pixels (..., 2), planar depth (...))."""
    cam = points_to_camera(camera_to_world, points_world)
    return project_camera_points(K, cam), cam[..., 2]


def pixel_rays(K: Tensor, camera_to_world: Tensor, uv: Tensor) -> tuple[Tensor, Tensor]:
    """World rays through pixels uv (..., 2) -> (origins (..., 3), unit directions (..., 3))."""
    # K^-1 [u, v, 1] in closed form for an upper-triangular K (ONNX has no matrix inverse)
    y = (uv[..., 1:2] - K[1, 2]) / K[1, 1]
    x = (uv[..., 0:1] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    dirs_cam = torch.cat([x, y, torch.ones_like(x)], dim=-1)
    dirs_cam = dirs_cam / dirs_cam.norm(dim=-1, keepdim=True)
    dirs = dirs_cam @ camera_to_world[:3, :3].T
    return camera_to_world[:3, 3].expand_as(dirs), dirs


def grid_cell_centres(grid_h: int, grid_w: int, width: int, height: int, device=None,
                      dtype=torch.float32) -> Tensor:
    """Pixel coordinates (grid_h, grid_w, 2) of the YOLO cell centres of a W x H image.

    Cells are image fractions: cell (i, j) spans x in [j/Sw, (j+1)/Sw] of the image extent
    [-0.5, W-0.5], so its centre is at u = (j + 0.5) * W / Sw - 0.5 (the same fraction
    convention as ``dataset_spec.boxes.box_to_yolo``).
    """
    j = (torch.arange(grid_w, device=device, dtype=dtype) + 0.5) * (width / grid_w) - 0.5
    i = (torch.arange(grid_h, device=device, dtype=dtype) + 0.5) * (height / grid_h) - 0.5
    v, u = torch.meshgrid(i, j, indexing="ij")
    return torch.stack([u, v], dim=-1)


def pixel_to_cell(uv: Tensor, grid_h: int, grid_w: int, width: int, height: int) -> Tensor:
    """Pixels (..., 2) -> integer cell indices (..., 2) as (row, col)."""
    col = torch.floor((uv[..., 0] + 0.5) / width * grid_w).long()
    row = torch.floor((uv[..., 1] + 0.5) / height * grid_h).long()
    return torch.stack([row, col], dim=-1)


def project_to_views(K: Tensor, camera_to_world: Tensor, points: Tensor, width: int, height: int
                     ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Project world points (..., 3) into V views (K (V,3,3), c2w (V,4,4)).

    Returns (uv (V, ..., 2), points in each view's camera axes (V, ..., 3),
    planar depth (V, ...), valid (V, ...) bool = in front (z > MIN_DEPTH) and inside
    [-0.5, W-0.5] x [-0.5, H-0.5]).
    """
    V = K.shape[0]
    w2c = invert_rigid(camera_to_world)  # (V, 4, 4)
    flat = points.reshape(1, -1, 3)
    cam = flat @ w2c[:, :3, :3].transpose(1, 2) + w2c[:, None, :3, 3]  # (V, N, 3)
    z = cam[..., 2]
    front = z > MIN_DEPTH
    safe_z = torch.where(front, z, torch.ones_like(z))
    xy = cam[..., :2] / safe_z[..., None]
    uv = xy @ K[:, :2, :2].transpose(1, 2) + K[:, None, :2, 2]
    inside = (uv[..., 0] >= -0.5) & (uv[..., 0] <= width - 0.5) & (uv[..., 1] >= -0.5) & (uv[..., 1] <= height - 0.5)
    valid = front & inside
    uv = torch.where(valid[..., None], uv, torch.zeros_like(uv))
    shape = points.shape[:-1]
    return (uv.reshape(V, *shape, 2), cam.reshape(V, *shape, 3), z.reshape(V, *shape), valid.reshape(V, *shape))


@dataclass
class Cameras:
    """V views' cameras at one image size: the torch twin of ``dataset_spec.CameraInfo`` (intrinsics
    (V, 3, 3) and camera-to-world (V, 4, 4), OpenCV axes) that the models project and cast rays with."""

    K: Tensor
    camera_to_world: Tensor
    width: int
    height: int

    def __len__(self) -> int:
        return self.K.shape[0]

    def project(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """World points (..., 3) into every view: ``project_to_views``' (uv, camera points, depth, valid)."""
        return project_to_views(self.K, self.camera_to_world, points, self.width, self.height)

    def pixel_rays(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        """The same pixels (..., 2) of every view -> world origins and unit directions, (V, ..., 3) each."""
        o, d = zip(*(pixel_rays(self.K[v], self.camera_to_world[v], uv) for v in range(len(self))))
        return torch.stack(o), torch.stack(d)
