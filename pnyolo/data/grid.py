"""The encoded image and its YOLO grid: ``grid_for(320, 180, 1.0, 16)`` -> 320x180 pixels, 20x11 cells."""
from __future__ import annotations

from dataclasses import dataclass

from dataset_spec.cli_support import UserError
from pnyolo.config.checks import MAX_GRID_CELLS, MAX_IMAGE_SIDE


@dataclass(frozen=True)
class GridSpec:
    width: int  # encoded image size
    height: int
    grid_w: int
    grid_h: int


def grid_for(width: int, height: int, scale: float, cell_px: float) -> GridSpec:
    """The encoded size and grid of a ``width`` x ``height`` image; one line when either is beyond what an item may
    ask for (``MAX_IMAGE_SIDE``, ``MAX_GRID_CELLS``), before anything of that size exists."""
    w, h = max(1, round(width * scale)), max(1, round(height * scale))
    if max(w, h) > MAX_IMAGE_SIDE:
        raise UserError(f"data.image_scale {scale:g} makes {width}x{height} images {w}x{h} pixels, above "
                        f"{MAX_IMAGE_SIDE} a side")
    g = GridSpec(w, h, max(1, round(w / cell_px)), max(1, round(h / cell_px)))
    if g.grid_w * g.grid_h > MAX_GRID_CELLS:
        raise UserError(f"data.cell_px {cell_px:g} makes a {g.grid_w}x{g.grid_h} grid on {w}x{h} images, above "
                        f"{MAX_GRID_CELLS} cells")
    return g
