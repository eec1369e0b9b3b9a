"""The ground grids of the field's multi-view pedestrian datasets (Wildtrack, MultiviewX): where a
``positionID`` of their annotation files, and a ``grid_x grid_y`` of their ``gt.txt``, lies in world
metres, and back::

    grid = GRIDS["wildtrack"]                       # 480 x 1440 cells of 2.5 cm from (-3, -9) m
    grid.world_of_xy(grid.xy_of_position([1234]))   # [[-3 + 2.5 cm * (1234 % 480), -9 + 2.5 cm * (1234 // 480)]]
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .cli_support import UserError


@dataclass(frozen=True)
class GroundGrid:
    """A dataset's ground grid: ``nx`` x ``ny`` cells of ``cell_m`` metres, cell (0, 0) at world
    ``origin_m`` (x, y); a position number is ``x + nx * y``."""

    nx: int
    ny: int
    cell_m: float
    origin_m: tuple[float, float] = (0.0, 0.0)

    def cells(self, metres: float) -> float:
        return metres / self.cell_m

    def xy_of_position(self, position) -> np.ndarray:
        """Position numbers (N,) -> grid cells (N, 2) [x, y]; one-line error outside the grid."""
        pos = np.asarray(position, dtype=np.int64).reshape(-1)
        bad = pos[(pos < 0) | (pos >= self.nx * self.ny)]
        if len(bad):
            raise UserError(f"positionID {int(bad[0])} is outside the {self.nx} x {self.ny} ground grid")
        return np.stack([pos % self.nx, pos // self.nx], axis=1)

    def position_of_xy(self, xy) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.int64).reshape(-1, 2)
        return xy[:, 0] + self.nx * xy[:, 1]

    def world_of_xy(self, xy) -> np.ndarray:
        """Grid cells (N, 2) -> world metres (N, 2) on the ground."""
        return np.asarray(self.origin_m) + np.asarray(xy, dtype=np.float64).reshape(-1, 2) * self.cell_m

    def xy_of_world(self, world) -> np.ndarray:
        """World metres (N, 2) -> the nearest grid cells (N, 2), int."""
        return np.rint((np.asarray(world, dtype=np.float64).reshape(-1, 2) - self.origin_m) / self.cell_m).astype(np.int64)


# Facts: ../shared/reference/FACTS.md, "Real multi-view pedestrian datasets".
GRIDS = {"wildtrack": GroundGrid(480, 1440, 0.025, (-3.0, -9.0)), "multiviewx": GroundGrid(1000, 640, 0.025)}
