"""The encoded image and its YOLO grid: ``grid_for(320, 180, 1.0, 16)`` -> 320x180 pixels, 20x11 cells."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class GridSpec:
    width: int  # encoded image size
    height: int
    grid_w: int
    grid_h: int


def grid_for(width: int, height: int, scale: float, cell_px: float) -> GridSpec:
    w, h = max(1, round(width * scale)), max(1, round(height * scale))
    return GridSpec(w, h, max(1, round(w / cell_px)), max(1, round(h / cell_px)))
