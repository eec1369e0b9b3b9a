"""How each detection moves, from its track: a velocity and a nuScenes attribute for every detection of a sequence
(the full 3D state the devkit's AVE and AAE score), from the tracker that follows the detections over the frames.

    moved = with_motion(frames, fps=10.0, class_names=["car", "pedestrian"])   # [WorldDetections] of one sequence

Every detection given may start a track (they are the detector's at its operating point); a detection's velocity is
its track's after the frame's update (0 for a track's first detection: unknown), and its attribute is the export's
rule on its track (``dataset_spec.nuscenes_format.attribute_of``): moving above 0.5 m/s, else a vehicle stopped when
its track moves at some frame, parked when it never does, a pedestrian standing. A road user moving faces the way it
moves: a moving detection whose heading points against its velocity is turned by 180 degrees (a detector sees the
axis of a footprint better than which way along it a road user faces). A still (one frame, or no frame
rate) has no motion: every detection standing still, parked or standing, as the export labels a still.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from dataset_spec.nuscenes_format import MOVING_M_S, attribute_of
from pnyolo.decoding.detections import WorldDetections
from pnyolo.decoding.ground_tracker import EVERY_DETECTION, GroundTracker


def facing_motion(boxes: np.ndarray, velocities: np.ndarray) -> np.ndarray:
    """Boxes (N, 7) whose heading points against their velocity (N, 2) while they move (above ``MOVING_M_S``) turned
    by pi; the others as they are (a copy)."""
    boxes = np.array(boxes, dtype=np.float64, copy=True).reshape(-1, 7)
    v = np.asarray(velocities, dtype=np.float64).reshape(-1, 2)
    if len(boxes):
        moving = np.linalg.norm(v, axis=1) > MOVING_M_S
        against = np.cos(boxes[:, 6]) * v[:, 0] + np.sin(boxes[:, 6]) * v[:, 1] < 0
        boxes[moving & against, 6] += np.pi
        boxes[:, 6] = np.arctan2(np.sin(boxes[:, 6]), np.cos(boxes[:, 6]))
    return boxes


def with_motion(frames: list[WorldDetections], fps: float | None, class_names: list[str]) -> list[WorldDetections]:
    """``frames`` (one sequence's detections, in frame order) each with velocities and attributes (the docstring)."""
    if not fps or len(frames) < 2:
        return [replace(d, velocities=np.zeros((len(d), 2)),
                        attributes=[attribute_of(class_names[int(c)], None, False) for c in d.classes]) for d in frames]
    tracker = GroundTracker(fps, EVERY_DETECTION)
    velocities, tracks = [], []
    for f, d in enumerate(frames):
        states = tracker.step(f, d)
        velocities.append(np.array([s[2:] for s, _ in states], dtype=np.float64).reshape(-1, 2))
        tracks.append(list(tracker.assigned))
    moves: dict[int, bool] = {}
    for v, ids in zip(velocities, tracks):
        for speed, track in zip(np.linalg.norm(v, axis=1), ids):
            if track is not None:
                moves[track] = moves.get(track, False) or bool(speed > MOVING_M_S)
    out = []
    for d, v, ids in zip(frames, velocities, tracks):
        speeds = np.linalg.norm(v, axis=1)
        out.append(replace(d, boxes=facing_motion(d.boxes, v), velocities=v, attributes=[
            attribute_of(class_names[int(c)], float(s), moves.get(t, False)) for c, s, t in zip(d.classes, speeds, ids)]))
    return out
