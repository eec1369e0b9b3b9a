"""What a detector returns: detections in one view (2D boxes, with distances and world boxes where
the model has them) and detections in the world frame (3D boxes). Every layer may import these.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class ViewDetections:
    boxes: np.ndarray  # (P, 4) pixels
    scores: np.ndarray  # (P,)
    classes: np.ndarray  # (P,) int
    distances: np.ndarray | None = None  # (P,) metres
    centres: np.ndarray | None = None  # (P, 3) world box centres (models with 3D outputs; NaN: none)
    world_boxes: np.ndarray | None = None  # (P, 7) [cx, cy, cz, length, width, height, yaw] (bev models)
    velocities: np.ndarray | None = None  # (P, 2) ground velocities, m/s (results that state them)
    attributes: list[str] | None = None  # (P,) nuScenes attribute names (results that state them)

    def above(self, threshold: float) -> "ViewDetections":
        """The detections scoring at least ``threshold``. Greedy NMS never lets a lower score
        suppress a higher one, so NMS at a low threshold followed by this equals NMS at ``threshold``."""
        return self.take(np.asarray(self.scores) >= threshold)

    def take(self, keep) -> "ViewDetections":
        picked = np.arange(len(self.scores))[keep]
        return ViewDetections(self.boxes[keep], self.scores[keep], self.classes[keep],
                              None if self.distances is None else self.distances[keep],
                              None if self.centres is None else self.centres[keep],
                              None if self.world_boxes is None else self.world_boxes[keep],
                              None if self.velocities is None else self.velocities[keep],
                              None if self.attributes is None else [self.attributes[i] for i in picked])



@dataclass
class WorldDetections:
    boxes: np.ndarray  # (P, 7) world [cx, cy, cz, length, width, height, yaw]
    scores: np.ndarray  # (P,)
    classes: np.ndarray  # (P,) int
    velocities: np.ndarray | None = None  # (P, 2) ground velocities, m/s (results that state them)
    attributes: list[str] | None = None  # (P,) nuScenes attribute names (results that state them)

    def __len__(self) -> int:
        return len(self.scores)

    def take(self, keep) -> "WorldDetections":
        picked = np.arange(len(self.scores))[keep]
        return WorldDetections(self.boxes[keep], self.scores[keep], self.classes[keep],
                               None if self.velocities is None else self.velocities[keep],
                               None if self.attributes is None else [self.attributes[i] for i in picked])

    def above(self, threshold: float) -> "WorldDetections":
        """The detections scoring at least ``threshold``."""
        return self.take(np.asarray(self.scores) >= threshold)

    @staticmethod
    def empty() -> "WorldDetections":
        return WorldDetections(np.zeros((0, 7)), np.zeros(0), np.zeros(0, dtype=np.int64))

    @staticmethod
    def concat(parts: list["WorldDetections"]) -> "WorldDetections":
        stated = bool(parts) and all(p.velocities is not None for p in parts)  # velocities kept when all state them
        named = bool(parts) and all(p.attributes is not None for p in parts)
        return WorldDetections(np.concatenate([p.boxes.reshape(-1, 7) for p in parts]),
                               np.concatenate([p.scores for p in parts]),
                               np.concatenate([p.classes for p in parts]).astype(np.int64),
                               np.concatenate([p.velocities.reshape(-1, 2) for p in parts]) if stated else None,
                               [a for p in parts for a in p.attributes] if named else None)


def union(a: ViewDetections, b: ViewDetections) -> ViewDetections:
    """``a``'s detections then ``b``'s (distances and centres NaN where one side has none)."""

    def dist(d: ViewDetections) -> np.ndarray:
        return np.full(len(d.boxes), np.nan) if d.distances is None else np.asarray(d.distances, dtype=np.float64)

    def centres(d: ViewDetections) -> np.ndarray:
        return np.full((len(d.boxes), 3), np.nan) if d.centres is None else np.asarray(d.centres, dtype=np.float64)

    return ViewDetections(np.concatenate([np.asarray(a.boxes, dtype=np.float64).reshape(-1, 4),
                                          np.asarray(b.boxes, dtype=np.float64).reshape(-1, 4)]),
                          np.concatenate([np.asarray(a.scores, dtype=np.float64), np.asarray(b.scores, dtype=np.float64)]),
                          np.concatenate([np.asarray(a.classes, dtype=np.int64), np.asarray(b.classes, dtype=np.int64)]),
                          np.concatenate([dist(a), dist(b)]),
                          None if a.centres is None and b.centres is None else np.concatenate([centres(a), centres(b)]))
