"""3D boxes into camera views for many boxes and views at once, on the boxes' device: the torch twin of
``dataset_spec.boxes.box_in_view`` and ``frustum_fraction`` (the rule a labelled road user follows), tested
against them, so putting a frame's detections into its views is a few tensor operations instead of a Python
call per detection and view::

    seen = boxes_in_views(boxes, K, camera_to_world, width, height, near, far)   # BoxViews, (V, P) each
    seen.box[v, p], seen.valid[v, p], seen.distance[v, p], seen.holds_camera[v, p]
    share = in_frame(boxes, K, camera_to_world, width, height, near, asked)     # (V, P), only where ``asked``
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from dataset_spec.boxes import BOX_EDGES, _CORNER_SIGNS

FRUSTUM_SAMPLES = 24  # grid cells per side that measure the in-frame share of a box not wholly in view
PAIRS_AT_ONCE = 32  # (view, box) pairs whose grids are measured together


@dataclass
class BoxViews:
    box: Tensor  # (V, P, 4) [x0, y0, x1, y1] near-clipped, projected, clipped to the image (NaN where not valid)
    valid: Tensor  # (V, P) bool: some of it in front of the near plane falls inside the image, not beyond far
    distance: Tensor  # (V, P) metres from the camera to the box centre
    holds_camera: Tensor  # (V, P) bool: the camera lies inside the box (the car carrying it)


def box_corners(boxes: Tensor) -> Tensor:
    """(P, 7) [cx, cy, cz, length, width, height, yaw] -> (P, 8, 3) corners in ``dataset_spec.boxes``' order."""
    signs = torch.as_tensor(_CORNER_SIGNS, dtype=boxes.dtype, device=boxes.device)
    local = signs * (boxes[:, None, 3:6] / 2)
    c, s = torch.cos(boxes[:, 6]), torch.sin(boxes[:, 6])
    x = local[..., 0] * c[:, None] - local[..., 1] * s[:, None]
    y = local[..., 0] * s[:, None] + local[..., 1] * c[:, None]
    return torch.stack([x, y, local[..., 2]], dim=-1) + boxes[:, None, :3]


def _to_camera(points: Tensor, camera_to_world: Tensor) -> Tensor:
    """World points (P, N, 3) -> camera points (V, P, N, 3)."""
    R, t = camera_to_world[:, :3, :3], camera_to_world[:, :3, 3]
    return torch.einsum("vji,vpnj->vpni", R, points[None] - t[:, None, None, :])


def _pixels(K: Tensor, cam: Tensor) -> Tensor:
    """Camera points (V, ...) -> pixels (V, ..., 2) (meaningless where z <= 0)."""
    shape = (K.shape[0],) + (1,) * (cam.dim() - 2)
    fx, fy, cx, cy, skew = (K[:, i, j].reshape(shape) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2), (0, 1)))
    x, y = cam[..., 0] / cam[..., 2], cam[..., 1] / cam[..., 2]
    return torch.stack([fx * x + skew * y + cx, fy * y + cy], dim=-1)


def _in_view(K: Tensor, cam: Tensor, width: int, height: int, near: Tensor) -> Tensor:
    """(V, ...) bool: points in front of ``near`` (V,) that project inside the image."""
    front = cam[..., 2] >= near.reshape((-1,) + (1,) * (cam.dim() - 2))
    safe = torch.where(front[..., None], cam, torch.tensor([0.0, 0.0, 1.0], dtype=cam.dtype, device=cam.device))
    uv = _pixels(K, safe)
    return front & (uv[..., 0] >= -0.5) & (uv[..., 0] <= width - 0.5) & (uv[..., 1] >= -0.5) & (uv[..., 1] <= height - 0.5)


def boxes_in_views(boxes: Tensor, K: Tensor, camera_to_world: Tensor, width: int, height: int, near: Tensor,
                   far: Tensor) -> BoxViews:
    """Every box (P, 7) in every view (K (V, 3, 3), camera_to_world (V, 4, 4), near and far (V,) metres) as a
    camera's labels see it (``dataset_spec.boxes.box_in_view``; near planes below 1e-4 m taken as 1e-4)."""
    near = near.clamp_min(1e-4)
    corners = box_corners(boxes)
    cam = _to_camera(corners, camera_to_world)  # (V, P, 8, 3)
    n = near[:, None, None]
    edges = torch.as_tensor(BOX_EDGES, device=boxes.device)
    p0, p1 = cam[:, :, edges[:, 0]], cam[:, :, edges[:, 1]]  # (V, P, 12, 3)
    z0, z1 = p0[..., 2], p1[..., 2]
    keep = (z0 >= n) | (z1 >= n)
    denom = torch.where((z1 - z0).abs() < 1e-12, torch.ones_like(z0), z1 - z0)
    crossing = p0 + ((n - z0) / denom).clamp(0.0, 1.0)[..., None] * (p1 - p0)
    q0 = torch.where((z0 >= n)[..., None], p0, crossing)
    q1 = torch.where((z1 >= n)[..., None], p1, crossing)
    uv = _pixels(K, torch.cat([q0, q1], dim=2))  # (V, P, 24, 2)
    kept = torch.cat([keep, keep], dim=2)[..., None]
    lo = torch.where(kept, uv, torch.full_like(uv, torch.inf)).amin(dim=2)
    hi = torch.where(kept, uv, torch.full_like(uv, -torch.inf)).amax(dim=2)
    box = torch.stack([lo[..., 0].clamp_min(-0.5), lo[..., 1].clamp_min(-0.5), hi[..., 0].clamp_max(width - 0.5),
                       hi[..., 1].clamp_max(height - 0.5)], dim=-1)
    valid = keep.any(dim=2) & (box[..., 2] > box[..., 0]) & (box[..., 3] > box[..., 1]) \
        & ~(cam[..., 2].amin(dim=2) > far[:, None])
    centre = camera_to_world[:, None, :3, 3]
    distance = (boxes[None, :, :3] - centre).norm(dim=-1)
    holds = _inside(centre[:, 0], boxes)
    return BoxViews(torch.where(valid[..., None], box, torch.nan), valid, distance, holds)


def _inside(points: Tensor, boxes: Tensor) -> Tensor:
    """(V, P) bool: point v (V, 3) inside box p (P, 7)."""
    d = points[:, None, :] - boxes[None, :, :3]
    c, s = torch.cos(boxes[:, 6]), torch.sin(boxes[:, 6])
    local = torch.stack([d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c, d[..., 2]], dim=-1)
    return (local.abs() <= boxes[None, :, 3:6] / 2).all(dim=-1)


def in_frame(boxes: Tensor, K: Tensor, camera_to_world: Tensor, width: int, height: int, near: Tensor,
             asked: Tensor) -> Tensor:
    """(V, P) in-frame share (``dataset_spec.boxes.frustum_fraction``) where ``asked`` (V, P) (0 elsewhere): 1 when
    all 8 corners are in view, else the share of a FRUSTUM_SAMPLES^3 grid of cell centres in view."""
    near = near.clamp_min(1e-4)
    cam = _to_camera(box_corners(boxes), camera_to_world)
    share = (_in_view(K, cam, width, height, near).all(dim=2) & asked).to(boxes.dtype)
    pairs_v, pairs_p = torch.nonzero(asked & (share < 1), as_tuple=True)
    t = (torch.arange(FRUSTUM_SAMPLES, dtype=boxes.dtype, device=boxes.device) + 0.5) / FRUSTUM_SAMPLES - 0.5
    grid = torch.stack(torch.meshgrid(t, t, t, indexing="ij"), dim=-1).reshape(-1, 3)
    for start in range(0, len(pairs_v), PAIRS_AT_ONCE):  # memory bounded: 32 pairs x 13824 points at a time
        v, p = pairs_v[start:start + PAIRS_AT_ONCE], pairs_p[start:start + PAIRS_AT_ONCE]
        local = grid[None] * boxes[p, None, 3:6]  # (N, G, 3)
        c, s = torch.cos(boxes[p, 6])[:, None], torch.sin(boxes[p, 6])[:, None]
        world = torch.stack([local[..., 0] * c - local[..., 1] * s, local[..., 0] * s + local[..., 1] * c,
                             local[..., 2]], dim=-1) + boxes[p, None, :3]
        R, tr = camera_to_world[v, :3, :3], camera_to_world[v, :3, 3]
        pts = torch.einsum("nji,ngj->ngi", R, world - tr[:, None, :])  # (N, G, 3) in each pair's camera
        front = pts[..., 2] >= near[v][:, None]
        safe = torch.where(front[..., None], pts, torch.tensor([0.0, 0.0, 1.0], dtype=pts.dtype, device=pts.device))
        kv = K[v]
        x, y = safe[..., 0] / safe[..., 2], safe[..., 1] / safe[..., 2]
        u = kv[:, 0, 0, None] * x + kv[:, 0, 1, None] * y + kv[:, 0, 2, None]
        w = kv[:, 1, 1, None] * y + kv[:, 1, 2, None]
        inside = front & (u >= -0.5) & (u <= width - 0.5) & (w >= -0.5) & (w <= height - 0.5)
        share[v, p] = inside.to(boxes.dtype).mean(dim=1)
    return share
