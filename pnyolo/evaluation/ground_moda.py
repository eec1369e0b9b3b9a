"""The field's ground-plane evaluation (Wildtrack, MultiviewX, MVDet and its successors): rows of
``frame grid_x grid_y`` for the ground truth (``gt.txt``) and for the detections, matched per frame
one to one (Hungarian, on the distance between grid positions) within 0.5 m, as their evaluators do::

    grid = GRIDS["wildtrack"]                                  # 2.5 cm cells, the dataset's origin
    scores = clear_mod(read_rows("gt.txt"), read_rows("test.txt"), grid.cells(0.5))
    scores["moda"], scores["modp"], scores["precision"], scores["recall"]

MODA = 1 - (FP + FN) / N_gt; MODP = mean over matches of 1 - d / threshold; precision TP / (TP + FP);
recall TP / N_gt. A pair at exactly the threshold matches (the published ports mask distances
above it). ``GroundGrid`` turns positions (``positionID`` of the annotation files) and grid cells
into world metres and back.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dataset_spec.atomic import atomic_write_text
from dataset_spec.cli_support import UserError
from pnyolo.evaluation.metrics_3d import matches_within


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


def read_rows(path: str | Path) -> np.ndarray:
    """A ``frame grid_x grid_y`` file (whitespace or commas; later columns ignored) -> (N, 3) float;
    one-line errors naming the file and the line."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path} does not exist")
    rows = []
    for k, line in enumerate(path.read_text().splitlines(), 1):
        parts = line.replace(",", " ").split()
        if not parts:
            continue
        try:
            rows.append([float(v) for v in parts[:3]])
        except ValueError:
            raise UserError(f"{path}:{k}: expected 'frame grid_x grid_y' numbers, got {line.strip()!r}") from None
        if len(rows[-1]) < 3:
            raise UserError(f"{path}:{k}: expected 'frame grid_x grid_y', got {line.strip()!r}")
    return np.asarray(rows, dtype=np.float64).reshape(-1, 3)


def write_rows(path: str | Path, rows) -> None:
    """(N, 3) ``frame grid_x grid_y`` rows as the field's evaluators read them (integers, atomic)."""
    rows = np.asarray(rows).reshape(-1, 3)
    atomic_write_text(Path(path), "".join(f"{int(f)} {int(round(x))} {int(round(y))}\n" for f, x, y in rows))


def clear_mod(gt: np.ndarray, pred: np.ndarray, threshold: float) -> dict:
    """MODA, MODP, precision and recall of ``pred`` against ``gt`` ((N, 3) rows, distances and
    ``threshold`` in the rows' units: grid cells), every frame of either counted."""
    gt, pred = np.asarray(gt, dtype=np.float64).reshape(-1, 3), np.asarray(pred, dtype=np.float64).reshape(-1, 3)
    tp = fp = fn = 0
    closeness = []
    for frame in np.unique(np.concatenate([gt[:, 0], pred[:, 0]])):
        g, p = gt[gt[:, 0] == frame, 1:], pred[pred[:, 0] == frame, 1:]
        d = np.hypot(p[:, None, 0] - g[None, :, 0], p[:, None, 1] - g[None, :, 1])
        found = matches_within(d, threshold)
        tp, fp, fn = tp + len(found), fp + len(p) - len(found), fn + len(g) - len(found)
        closeness += [1 - dist / threshold for _, _, dist in found]
    n_gt = len(gt)
    return {"moda": 1 - (fp + fn) / n_gt if n_gt else None, "modp": float(np.mean(closeness)) if closeness else None,
            "precision": tp / (tp + fp) if tp + fp else None, "recall": tp / n_gt if n_gt else None,
            "tp": tp, "fp": fp, "fn": fn, "n_gt": n_gt}
