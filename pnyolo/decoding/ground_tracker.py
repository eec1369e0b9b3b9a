"""Tracking by detection on the ground plane: one constant-velocity Kalman filter per track, detections
assigned to tracks by minimum cost (scipy's ``linear_sum_assignment``) within a gate, with rules for
birth and death.

    tracker = GroundTracker(fps=10.0)
    for frame, dets in enumerate(per_frame):        # WorldDetections of each frame
        tracker.step(frame, dets)
    rows = tracker.rows()                          # TrackRow: frame, track id, class, x, y, vx, vy, score

The rules: a track's state is (x, y, vx, vy) with white-acceleration process noise; each frame every track
is predicted, then detections of its class whose centre lies within ``gate_m`` of the prediction are
assigned at least total distance. An unassigned detection starts a tentative track; a track seen
``min_hits`` times is confirmed, and then reported from its first detection on (an offline tracker can
look back); a track missed ``max_missed`` frames in a row ends (a confirmed track coasts through the
frames in between, keeping its id, and is not reported there).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from pnyolo.decoding.detections import WorldDetections

GATE_M, MIN_HITS, MAX_MISSED = 2.0, 2, 3
ACCEL_SIGMA = 3.0  # m/s^2: how fast a road user may change its velocity (process noise)
MEASURE_SIGMA = 0.5  # m: a detection's position error


@dataclass
class TrackRow:
    frame: int
    track: int
    cls: int
    x: float
    y: float
    vx: float
    vy: float
    score: float


@dataclass
class _Track:
    id: int
    cls: int
    state: np.ndarray  # (4,) x, y, vx, vy
    cov: np.ndarray  # (4, 4)
    hits: int = 1
    missed: int = 0
    rows: list[TrackRow] = field(default_factory=list)


class GroundTracker:
    def __init__(self, fps: float, gate_m: float = GATE_M, min_hits: int = MIN_HITS, max_missed: int = MAX_MISSED):
        if not fps > 0 or not gate_m > 0 or min_hits < 1 or max_missed < 0:
            raise ValueError("fps > 0, gate_m > 0, min_hits >= 1, max_missed >= 0")
        dt = 1.0 / fps
        self.F = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=np.float64)
        q = np.array([[dt ** 4 / 4, dt ** 3 / 2], [dt ** 3 / 2, dt ** 2]]) * ACCEL_SIGMA ** 2
        self.Q = np.zeros((4, 4))
        self.Q[np.ix_([0, 2], [0, 2])] = q
        self.Q[np.ix_([1, 3], [1, 3])] = q
        self.H = np.eye(2, 4)
        self.R = np.eye(2) * MEASURE_SIGMA ** 2
        self.gate_m, self.min_hits, self.max_missed = gate_m, min_hits, max_missed
        self.tracks: list[_Track] = []
        self.finished: list[_Track] = []
        self.next_id = 1

    def step(self, frame: int, dets: WorldDetections) -> list[tuple[np.ndarray, np.ndarray]]:
        """Predict every track to ``frame``, assign ``dets`` (their ground centres), update, start and end tracks;
        returns each detection's track after the step: its state ((4,) x, y, vx, vy; a new track's velocity 0)
        and covariance (4, 4)."""
        for t in self.tracks:
            t.state, t.cov = self.F @ t.state, self.F @ t.cov @ self.F.T + self.Q
        xy = dets.boxes[:, :2] if len(dets) else np.zeros((0, 2))
        pairs = self._assign(xy, dets.classes)
        taken, used = set(), {}
        for ti, di in pairs:
            self._update(self.tracks[ti], frame, xy[di], float(dets.scores[di]))
            taken.add(ti)
            used[di] = self.tracks[ti]
        for ti, t in enumerate(self.tracks):
            if ti not in taken:
                t.missed += 1
        ended = [t for t in self.tracks if t.missed > self.max_missed]
        self.finished += [t for t in ended if t.hits >= self.min_hits]
        self.tracks = [t for t in self.tracks if t.missed <= self.max_missed]
        for di in range(len(xy)):
            if di not in used:
                used[di] = self._birth(frame, xy[di], int(dets.classes[di]), float(dets.scores[di]))
        return [(used[di].state.copy(), used[di].cov.copy()) for di in range(len(xy))]

    def _assign(self, xy: np.ndarray, classes: np.ndarray) -> list[tuple[int, int]]:
        if not self.tracks or not len(xy):
            return []
        pred = np.array([t.state[:2] for t in self.tracks])
        cost = np.linalg.norm(pred[:, None, :] - xy[None, :, :], axis=2)
        same = np.array([t.cls for t in self.tracks])[:, None] == np.asarray(classes)[None, :]
        cost = np.where(same & (cost <= self.gate_m), cost, 1e6)
        rows, cols = linear_sum_assignment(cost)
        return [(int(r), int(c)) for r, c in zip(rows, cols) if cost[r, c] < 1e6]

    def _update(self, t: _Track, frame: int, z: np.ndarray, score: float) -> None:
        S = self.H @ t.cov @ self.H.T + self.R
        gain = t.cov @ self.H.T @ np.linalg.inv(S)
        t.state = t.state + gain @ (z - self.H @ t.state)
        t.cov = (np.eye(4) - gain @ self.H) @ t.cov
        t.hits, t.missed = t.hits + 1, 0
        t.rows.append(TrackRow(frame, t.id, t.cls, *(float(v) for v in t.state), score))

    def _birth(self, frame: int, z: np.ndarray, cls: int, score: float) -> _Track:
        cov = np.diag([MEASURE_SIGMA ** 2, MEASURE_SIGMA ** 2, 25.0, 25.0])  # velocity unknown: up to ~5 m/s
        t = _Track(self.next_id, cls, np.array([z[0], z[1], 0.0, 0.0]), cov)
        t.rows.append(TrackRow(frame, t.id, cls, float(z[0]), float(z[1]), 0.0, 0.0, score))
        self.next_id += 1
        self.tracks.append(t)
        return t

    def rows(self) -> list[TrackRow]:
        """Every confirmed track's rows (the frames it was detected in), by frame and track id."""
        done = self.finished + [t for t in self.tracks if t.hits >= self.min_hits]
        return sorted((r for t in done for r in t.rows), key=lambda r: (r.frame, r.track))

    def velocities(self) -> dict[int, np.ndarray]:
        """Each live track's velocity now (m/s): what a car's message v2 would carry."""
        return {t.id: t.state[2:].copy() for t in self.tracks}
