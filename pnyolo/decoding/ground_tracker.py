"""Tracking by detection on the ground plane (AB3DMOT's filter, ByteTrack's two stages): one constant-velocity
Kalman filter per track, detections assigned to tracks by minimum cost (scipy's ``linear_sum_assignment``) within
a gate on the predicted state's uncertainty, confident detections starting tracks and weak ones only continuing
them, and a score per track for the devkit's AMOTA.

    tracker = GroundTracker(fps=10.0, point=TrackerPoint(start=0.4, keep=0.1))
    for frame, dets in enumerate(per_frame):        # WorldDetections of each frame (scores from point.keep up)
        tracker.step(frame, dets)
    rows = tracker.rows()                          # TrackRow: frame, track id, class, x, y, vx, vy, track score

The rules (``TrackerPoint``, chosen on validation by ``pnyolo.tracking.choice``): every track is predicted to the
frame; first the detections scoring at least ``start`` are assigned to every live track of their class, then those
scoring at least ``keep`` (and less than ``start``) to the confirmed tracks still unassigned. A detection and a
track pair only within ``gate`` standard deviations of the track's predicted position (the Mahalanobis distance
under the innovation covariance: a new track, whose velocity is unknown, reaches further than an old one). A
confident detection left over starts a tentative track (with the detection's velocity where the detector gives
one); a weak one starts nothing, so noise alone starts no track while an occluded road user's weak detections keep
its confirmed track alive. A track is confirmed at ``min_hits`` detections and reported from its first on (an
offline tracker looks back); a tentative track missed once ends; a confirmed one coasts up to ``max_missed`` frames
(not reported there). A track's score is the mean of its detections' scores counting one more of 0 (a track of one
detection at 0.8 scores 0.4, of five at 0.8 0.67): the devkit's AMOTA ranks whole tracks by it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from pnyolo.decoding.detections import WorldDetections

ACCEL_SIGMA = 3.0  # m/s^2: how fast a road user may change its velocity (process noise)
MEASURE_SIGMA = 0.5  # m: a detection's position error
UNKNOWN_SPEED_SIGMA = 5.0  # m/s: a new track's velocity uncertainty without the detector's velocity
STATED_SPEED_SIGMA = 1.0  # m/s: with the detector's velocity


@dataclass(frozen=True)
class TrackerPoint:
    """The tracker's operating point: ``start`` (a detection this confident starts or continues a track), ``keep``
    (at least this, it only continues a confirmed one), ``min_hits`` (detections that confirm a track),
    ``max_missed`` (frames a confirmed track coasts), ``gate`` (standard deviations of the predicted position)."""

    start: float = 0.4
    keep: float = 0.1
    min_hits: int = 2
    max_missed: int = 3
    gate: float = 3.0

    def __post_init__(self):
        if not (0 <= self.keep <= self.start <= 1 and self.min_hits >= 1 and self.max_missed >= 0 and self.gate > 0):
            raise ValueError(f"tracker point: 0 <= keep <= start <= 1, min_hits >= 1, max_missed >= 0, gate > 0; "
                             f"got {self}")

    @classmethod
    def at_detection(cls, threshold: float) -> "TrackerPoint":
        """The point that starts tracks from a detector's own threshold (what its operating point calls a
        detection) and continues them from half of it: the default where no validation sequences choose one."""
        return cls(start=threshold, keep=threshold / 2)

    def as_dict(self) -> dict:
        return {"start": self.start, "keep": self.keep, "min_hits": self.min_hits, "max_missed": self.max_missed,
                "gate": self.gate}


EVERY_DETECTION = TrackerPoint(start=0.0, keep=0.0)  # every detection given may start a track: its caller chose them


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
    scores: list[float] = field(default_factory=list)
    missed: int = 0
    rows: list[TrackRow] = field(default_factory=list)

    @property
    def hits(self) -> int:
        return len(self.scores)

    @property
    def score(self) -> float:
        """The mean of its detections' scores with one more of 0: short tracks count less."""
        return sum(self.scores) / (len(self.scores) + 1)


class GroundTracker:
    def __init__(self, fps: float, point: TrackerPoint = TrackerPoint()):
        if not fps > 0:
            raise ValueError("fps > 0")
        dt = 1.0 / fps
        self.F = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=np.float64)
        q = np.array([[dt ** 4 / 4, dt ** 3 / 2], [dt ** 3 / 2, dt ** 2]]) * ACCEL_SIGMA ** 2
        self.Q = np.zeros((4, 4))
        self.Q[np.ix_([0, 2], [0, 2])] = q
        self.Q[np.ix_([1, 3], [1, 3])] = q
        self.H = np.eye(2, 4)
        self.R = np.eye(2) * MEASURE_SIGMA ** 2
        self.point = point
        self.tracks: list[_Track] = []
        self.finished: list[_Track] = []
        self.next_id = 1
        self.assigned: list[int | None] = []  # the last step's detections' track ids (None: none)

    def step(self, frame: int, dets: WorldDetections) -> list[tuple[np.ndarray, np.ndarray]]:
        """Predict every track to ``frame``, assign ``dets`` (their ground centres) in two stages, update, start and
        end tracks; returns each detection's state after the step ((4,) x, y, vx, vy and covariance (4, 4)): its
        track's, or (a weak detection that continued none) its own with an unknown velocity."""
        p = self.point
        for t in self.tracks:
            t.state, t.cov = self.F @ t.state, self.F @ t.cov @ self.F.T + self.Q
        n = len(dets)
        xy = dets.boxes[:, :2] if n else np.zeros((0, 2))
        scores, classes = np.asarray(dets.scores, dtype=np.float64), np.asarray(dets.classes)
        strong = [d for d in range(n) if scores[d] >= p.start]
        weak = [d for d in range(n) if p.keep <= scores[d] < p.start]
        first = self._assign(list(range(len(self.tracks))), strong, xy, classes)
        left = [ti for ti in range(len(self.tracks)) if ti not in first.values() and self.tracks[ti].hits >= p.min_hits]
        second = self._assign(left, weak, xy, classes)
        used = {}
        for di, ti in {**first, **second}.items():
            self._update(self.tracks[ti], frame, xy[di], float(scores[di]))
            used[di] = self.tracks[ti]
        taken = set(first.values()) | set(second.values())
        for ti, t in enumerate(self.tracks):
            if ti not in taken:
                t.missed += 1
        ended = [t.missed > (p.max_missed if t.hits >= p.min_hits else 0) for t in self.tracks]
        self.finished += [t for t, end in zip(self.tracks, ended) if end and t.hits >= p.min_hits]
        self.tracks = [t for t, end in zip(self.tracks, ended) if not end]
        for di in strong:
            if di not in used:
                used[di] = self._birth(frame, xy[di], int(classes[di]), float(scores[di]), _velocity(dets, di))
        self.assigned = [used[d].id if d in used else None for d in range(n)]
        return [(used[d].state.copy(), used[d].cov.copy()) if d in used else _unknown(xy[d], _velocity(dets, d))
                for d in range(n)]

    def _assign(self, tracks: list[int], detections: list[int], xy: np.ndarray, classes: np.ndarray) -> dict[int, int]:
        """{detection: track} of least total Mahalanobis distance within the gate (same class only)."""
        if not tracks or not detections:
            return {}
        cost = np.full((len(tracks), len(detections)), np.inf)
        for i, ti in enumerate(tracks):
            t = self.tracks[ti]
            S_inv = np.linalg.inv(self.H @ t.cov @ self.H.T + self.R)
            d = xy[detections] - t.state[:2]
            m = np.sqrt(np.einsum("ni,ij,nj->n", d, S_inv, d))
            ok = (classes[detections] == t.cls) & (m <= self.point.gate)
            cost[i, ok] = m[ok]
        rows, cols = linear_sum_assignment(np.where(np.isfinite(cost), cost, 1e9))
        return {detections[c]: tracks[r] for r, c in zip(rows, cols) if np.isfinite(cost[r, c])}

    def _update(self, t: _Track, frame: int, z: np.ndarray, score: float) -> None:
        S = self.H @ t.cov @ self.H.T + self.R
        gain = t.cov @ self.H.T @ np.linalg.inv(S)
        t.state = t.state + gain @ (z - self.H @ t.state)
        t.cov = (np.eye(4) - gain @ self.H) @ t.cov
        t.scores.append(score)
        t.missed = 0
        t.rows.append(TrackRow(frame, t.id, t.cls, *(float(v) for v in t.state), score))

    def _birth(self, frame: int, z: np.ndarray, cls: int, score: float, velocity: np.ndarray | None) -> _Track:
        state, cov = _unknown(z, velocity)
        t = _Track(self.next_id, cls, state, cov, [score])
        t.rows.append(TrackRow(frame, t.id, cls, *(float(v) for v in state), score))
        self.next_id += 1
        self.tracks.append(t)
        return t

    def rows(self) -> list[TrackRow]:
        """Every confirmed track's rows (the frames it was detected in), by frame and track id, each with its
        track's score."""
        done = self.finished + [t for t in self.tracks if t.hits >= self.point.min_hits]
        rows = [TrackRow(r.frame, r.track, r.cls, r.x, r.y, r.vx, r.vy, t.score) for t in done for r in t.rows]
        return sorted(rows, key=lambda r: (r.frame, r.track))

    def velocities(self) -> dict[int, np.ndarray]:
        """Each live track's velocity now (m/s): what a car's message v2 would carry."""
        return {t.id: t.state[2:].copy() for t in self.tracks}


def _velocity(dets: WorldDetections, d: int) -> np.ndarray | None:
    return None if dets.velocities is None else np.asarray(dets.velocities[d], dtype=np.float64)


def _unknown(z: np.ndarray, velocity: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The state of a road user seen once at ``z``: its velocity the detector's, or 0 and unknown."""
    sigma = UNKNOWN_SPEED_SIGMA if velocity is None else STATED_SPEED_SIGMA
    v = np.zeros(2) if velocity is None else velocity
    return np.array([z[0], z[1], v[0], v[1]]), np.diag([MEASURE_SIGMA ** 2, MEASURE_SIGMA ** 2, sigma ** 2, sigma ** 2])
