"""The bird's-eye-view grid of the ``bev`` model and the pillar points it samples the views at.

A grid is axis-aligned in the world frame (metres, Z up): cell (iy, ix) spans
x in [x0 + ix * cell, x0 + (ix + 1) * cell) and y likewise; it covers every scored camera's view
out to ``range_m`` (the label distance limit), or fixed ``bounds`` from the config. Each cell holds
a pillar of points at the configured heights above the ground::

    grid = grid_for_cameras(Cameras(K, c2w, width, height), [0, 1, 2], cell=0.4, range_m=40.0)
    pts = pillar_points(grid, heights=[0.25, 0.75, 1.25], ground_z=0.0)     # (ny, nx, 3 heights, 3)
    uv, ok = project_pillars(K, c2w, pts, width, height)                     # (V, ny, nx, H, 2), (V, ny, nx, H)
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from dataset_spec.cli_support import UserError
from pnyolo.components.geometry import Cameras, project_to_views

GRID_MULTIPLE = 4  # cells per side are rounded up to this (the grid network halves the resolution)
FOOTPRINT_FAN = 9  # pixels across a camera's principal row whose horizontal directions bound its footprint
NEAR_M = 0.1  # pillar points closer than this (planar depth) to a camera do not count as seen by it


@dataclass(frozen=True)
class BevGrid:
    x0: float  # world x of the grid's lower edge, metres
    y0: float
    cell: float  # metres per cell
    nx: int
    ny: int

    def centres(self, device=None) -> Tensor:
        """(ny, nx, 2) world (x, y) of the cell centres."""
        x = self.x0 + (torch.arange(self.nx, device=device, dtype=torch.float32) + 0.5) * self.cell
        y = self.y0 + (torch.arange(self.ny, device=device, dtype=torch.float32) + 0.5) * self.cell
        yy, xx = torch.meshgrid(y, x, indexing="ij")
        return torch.stack([xx, yy], dim=-1)

    def mirrored(self) -> "BevGrid":
        """This grid mirrored in x = 0 (cell ix of the one is cell nx - 1 - ix of the other)."""
        return BevGrid(-(self.x0 + self.nx * self.cell), self.y0, self.cell, self.nx, self.ny)

    def cell_of(self, xy: Tensor) -> tuple[Tensor, Tensor]:
        """World (x, y) (..., 2) -> (iy, ix) long indices (may lie outside the grid)."""
        ix = torch.floor((xy[..., 0] - self.x0) / self.cell).long()
        iy = torch.floor((xy[..., 1] - self.y0) / self.cell).long()
        return iy, ix

    def inside(self, iy: Tensor, ix: Tensor) -> Tensor:
        return (ix >= 0) & (ix < self.nx) & (iy >= 0) & (iy < self.ny)


def _round_up(n: int) -> int:
    return max(GRID_MULTIPLE, int(math.ceil(n / GRID_MULTIPLE)) * GRID_MULTIPLE)


def view_footprint(K: Tensor, camera_to_world: Tensor, width: int, range_m: float, fan: int = FOOTPRINT_FAN) -> Tensor:
    """(fan + 1, 2) world (x, y) points bounding what a camera sees on the ground within ``range_m``:
    its centre and ``range_m`` along the horizontal directions of ``fan`` pixels across its
    principal row."""
    u = torch.linspace(-0.5, width - 0.5, fan, dtype=torch.float32)
    cam = torch.stack([(u - K[0, 2].cpu()) / K[0, 0].cpu(), torch.zeros_like(u), torch.ones_like(u)], dim=-1)
    rot, centre = camera_to_world[:3, :3].cpu().float(), camera_to_world[:3, 3].cpu().float()
    d = (cam @ rot.T)[:, :2]
    norm = d.norm(dim=-1, keepdim=True)
    d = torch.where(norm > 1e-6, d / norm.clamp_min(1e-6), torch.zeros_like(d))  # looking straight down: centre only
    return torch.cat([centre[None, :2], centre[None, :2] + range_m * d])


def grid_for_cameras(views: Cameras, cameras: list[int], cell: float, range_m: float, bounds: list[float] | None = None,
                     max_cells: int = 0) -> BevGrid:
    """The grid over the views of ``cameras`` (indices into ``views``) out to ``range_m``, or over ``bounds``
    [x_min, y_min, x_max, y_max]; snapped to whole cells, sides rounded up to a multiple of GRID_MULTIPLE.
    One-line errors for a grid over no camera or above ``max_cells``."""
    K, camera_to_world, width, height = views.K, views.camera_to_world, views.width, views.height
    if bounds is not None:
        x_min, y_min, x_max, y_max = (float(b) for b in bounds)
        if not x_min < x_max or not y_min < y_max:
            raise UserError(f"model.bev.bounds {list(bounds)}: expected [x_min, y_min, x_max, y_max]")
        if not _covers_any_view(K, camera_to_world, width, height, cameras, (x_min, y_min, x_max, y_max), range_m):
            centres = camera_to_world[cameras, :2, 3].cpu()
            raise UserError(f"model.bev.bounds {list(bounds)} cover no camera's view (cameras at x, y "
                            f"{[tuple(round(float(v), 1) for v in c) for c in centres]})")
    else:
        pts = torch.cat([view_footprint(K[c], camera_to_world[c], width, range_m) for c in cameras])
        (x_min, y_min), (x_max, y_max) = pts.min(dim=0).values.tolist(), pts.max(dim=0).values.tolist()
    return snapped_grid((x_min, y_min, x_max, y_max), cell, max_cells)


def snapped_grid(box, cell: float, max_cells: int = 0) -> BevGrid:
    """The grid over ``box`` (x_min, y_min, x_max, y_max): its corner on whole cells, its sides rounded
    up to a multiple of GRID_MULTIPLE; one line when it has more than ``max_cells``."""
    x_min, y_min, x_max, y_max = box
    x0, y0 = math.floor(x_min / cell) * cell, math.floor(y_min / cell) * cell
    nx, ny = _round_up(int(math.ceil((x_max - x0) / cell))), _round_up(int(math.ceil((y_max - y0) / cell)))
    if max_cells and nx * ny > max_cells:
        raise UserError(f"the bird's-eye-view grid would have {nx} x {ny} = {nx * ny} cells, above model.bev.max_cells "
                        f"{max_cells}: raise it, or lower model.bev.range_m / use larger model.bev.cell_m")
    return BevGrid(float(x0), float(y0), float(cell), nx, ny)


def _covers_any_view(K, camera_to_world, width, height, cameras, box, range_m: float) -> bool:
    """Whether some ground point inside ``box`` (x_min, y_min, x_max, y_max) lies in one of the
    views within ``range_m`` of its camera."""
    x_min, y_min, x_max, y_max = box
    xs, ys = torch.linspace(x_min, x_max, 33), torch.linspace(y_min, y_max, 33)
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    pts = torch.stack([xx, yy, torch.zeros_like(xx)], dim=-1).reshape(-1, 3)
    c2w = camera_to_world[cameras].cpu().float()
    _, _, _, ok = project_to_views(K[cameras].cpu().float(), c2w, pts, width, height)
    near = (pts[None, :, :2] - c2w[:, None, :2, 3]).norm(dim=-1) <= range_m
    return bool((ok & near).any())


def pillar_points(grid: BevGrid, heights: list[float], ground_z: float, device=None) -> Tensor:
    """(ny, nx, H, 3) world points: each cell centre at every height above ``ground_z``."""
    xy = grid.centres(device)
    z = ground_z + torch.tensor(heights, dtype=torch.float32, device=device)
    H = len(heights)
    return torch.cat([xy[:, :, None, :].expand(grid.ny, grid.nx, H, 2),
                      z[None, None, :, None].expand(grid.ny, grid.nx, H, 1)], dim=-1)


def project_pillars(K: Tensor, camera_to_world: Tensor, points: Tensor, width: int, height: int
                    ) -> tuple[Tensor, Tensor]:
    """Pillar points (..., 3) -> pixels in every view (V, ..., 2) and whether the view sees them
    (V, ...) bool: at least NEAR_M in front of the camera and inside the image."""
    uv, _, z, valid = project_to_views(K, camera_to_world, points, width, height)
    return uv, valid & (z >= NEAR_M)
