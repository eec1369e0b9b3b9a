"""The message a car sends for late fusion: a versioned binary format (docs/guide/cooperation.md).

    msg = CarMessage(sender=7, timestamp=12.5, pose=(x, y, z, yaw), pose_sigma=(0.2, 0.2, 0.2), detections=dets,
                     velocities=v, velocity_covariances=vc)
    data = encode(msg)                    # 48 bytes of header + 68 bytes per detection (version 2)
    back = decode(data)                   # version 1 and 2; MessageError (one line) for another, truncation, NaN
    now = back.at(13.0)                   # each detection moved to 13.0 s by its velocity, its covariance grown

Little-endian. Header: magic ``PNYM``, version (uint16), sender id (uint32), timestamp (float64 s),
sender pose x, y, z (m), yaw (rad), its uncertainty sigma_xy, sigma_z (m), sigma_yaw (deg) (float32
each), detection count (uint16). Each detection: class (uint8, 3 pad bytes), score, centre x, y, z,
size length, width, height, yaw, position covariance xx, xy, yy on the ground plane (float32 each);
version 2 adds the ground velocity vx, vy (m/s) and its covariance xx, xy, yy ((m/s)^2), from the
sender's own tracker. Version 1 messages (48 bytes a detection, no velocity) still decode, as standing
still with an unknown velocity. Values keep float32 precision (a relative error below 1e-7).
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from dataset_spec.cli_support import UserError
from pnyolo.decoding.world import WorldDetections
from pnyolo.cooperation.agreement import gather, noisy_or

MAGIC = b"PNYM"
VERSION = 2
HEADER = struct.Struct("<4sHIdfffffffH")
DETECTIONS = {1: struct.Struct("<B3x11f"), 2: struct.Struct("<B3x16f")}  # by format version
DETECTION = DETECTIONS[VERSION]
HEADER_BYTES, DETECTION_BYTES = HEADER.size, DETECTION.size
UNKNOWN_SPEED = 5.0  # m/s: the velocity's standard deviation a version-1 detection (no velocity) is given
MAX_CLASS = 254  # class 255 means nothing; a reader that knows its classes passes how many to ``decode``
# Each position covariance is taken between these (as standard deviations, metres) in fusion: a sender cannot
# claim certainty that outweighs everyone else without bound, nor a zero (singular) covariance.
COVARIANCE_FLOOR_M, COVARIANCE_CEILING_M = 0.1, 100.0


class MessageError(UserError):
    """A message that cannot be read (reported in one line)."""


@dataclass
class CarMessage:
    sender: int
    timestamp: float
    pose: tuple[float, float, float, float]  # x, y, z (m), yaw (rad) of the sending car
    pose_sigma: tuple[float, float, float]  # sigma_xy, sigma_z (m), sigma_yaw (deg) of that pose
    detections: WorldDetections
    covariances: np.ndarray | None = None  # (P, 3) xx, xy, yy (m^2); None: from the pose's uncertainty
    velocities: np.ndarray | None = None  # (P, 2) vx, vy (m/s); None: unknown (version 1)
    velocity_covariances: np.ndarray | None = None  # (P, 3) xx, xy, yy ((m/s)^2)

    def covariance(self) -> np.ndarray:
        return self.covariances if self.covariances is not None else position_covariance(
            self.detections.boxes, self.pose, self.pose_sigma)

    def velocity(self) -> tuple[np.ndarray, np.ndarray]:
        """(P, 2) velocities and (P, 3) their covariances: unknown ones standing still, ``UNKNOWN_SPEED`` uncertain."""
        n = len(self.detections)
        v = self.velocities if self.velocities is not None else np.zeros((n, 2))
        c = self.velocity_covariances if self.velocity_covariances is not None else \
            np.tile([UNKNOWN_SPEED ** 2, 0.0, UNKNOWN_SPEED ** 2], (n, 1))
        return np.asarray(v, dtype=np.float64).reshape(n, 2), np.asarray(c, dtype=np.float64).reshape(n, 3)

    def at(self, time_s: float) -> "CarMessage":
        """This message's detections where they are at ``time_s`` by constant velocity, their position
        covariance grown by the velocity's over the interval (the pose's uncertainty kept)."""
        dt = time_s - self.timestamp
        v, vc = self.velocity()
        boxes = self.detections.boxes.copy()
        boxes[:, :2] += v * dt
        moved = WorldDetections(boxes, self.detections.scores, self.detections.classes)
        return CarMessage(self.sender, time_s, self.pose, self.pose_sigma, moved, self.covariance() + vc * dt * dt,
                          self.velocities, self.velocity_covariances)


def position_covariance(boxes: np.ndarray, pose, pose_sigma, floor_m: float = 0.1) -> np.ndarray:
    """(P, 3) ground-plane covariance (xx, xy, yy) of detections placed through a pose known to
    ``pose_sigma``: the position error in every direction, plus the yaw error swinging each detection
    sideways by its distance from the car, plus a ``floor_m`` of the detector's own."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    d = boxes[:, :2] - np.asarray(pose[:2], dtype=np.float64)
    side = np.stack([-d[:, 1], d[:, 0]], axis=1)  # perpendicular to the line of sight, |side| = distance
    yaw_var = math.radians(pose_sigma[2]) ** 2
    base = pose_sigma[0] ** 2 + floor_m ** 2
    return np.stack([base + yaw_var * side[:, 0] ** 2, yaw_var * side[:, 0] * side[:, 1],
                     base + yaw_var * side[:, 1] ** 2], axis=1)


def message_bytes(detections: int, version: int = VERSION) -> int:
    """The size of a message carrying ``detections`` detections."""
    return HEADER_BYTES + detections * DETECTIONS[version].size


def encode(msg: CarMessage, version: int = VERSION) -> bytes:
    dets, cov = msg.detections, msg.covariance()
    v, vc = msg.velocity()
    out = [HEADER.pack(MAGIC, version, msg.sender, msg.timestamp, *msg.pose, *msg.pose_sigma, len(dets))]
    for k, (box, score, cls, c) in enumerate(zip(dets.boxes, dets.scores, dets.classes, cov)):
        extra = [*v[k], *vc[k]] if version >= 2 else []
        out.append(DETECTIONS[version].pack(int(cls), float(score), *(float(x) for x in (*box, *c, *extra))))
    return b"".join(out)


def _check_meaning(header: np.ndarray, rows: np.ndarray, version: int, num_classes: int | None) -> None:
    """What the format cannot mean, refused in one line: a class beyond the reader's (or 255), a score outside
    [0, 1], a size <= 0, a negative pose uncertainty, a position covariance that is not positive definite, a
    velocity covariance that is not positive semi-definite."""
    most = MAX_CLASS if num_classes is None else num_classes - 1
    if (header[5:] < 0).any():
        raise MessageError("message: a negative pose uncertainty")
    if len(rows) == 0:
        return
    if (rows[:, 0] > most).any():
        raise MessageError(f"message: class {int(rows[:, 0].max())} (the reader knows classes 0..{most})")
    if ((rows[:, 1] < 0) | (rows[:, 1] > 1)).any():
        raise MessageError("message: a score outside [0, 1]")
    if (rows[:, 5:8] <= 0).any():
        raise MessageError("message: a box size <= 0")
    xx, xy, yy = rows[:, 9], rows[:, 10], rows[:, 11]
    if ((xx <= 0) | (yy <= 0) | (xx * yy - xy * xy <= 0)).any():
        raise MessageError("message: a position covariance that is not positive definite")
    if version >= 2:
        vxx, vxy, vyy = rows[:, 14], rows[:, 15], rows[:, 16]
        if ((vxx < 0) | (vyy < 0) | (vxx * vyy - vxy * vxy < 0)).any():
            raise MessageError("message: a velocity covariance that is not positive semi-definite")


def decode(data: bytes, num_classes: int | None = None) -> CarMessage:
    """The message in ``data`` (one-line ``MessageError`` for anything that is not a whole, finite, meaningful
    message of a known version; ``num_classes``: the reader's, so a class beyond them is refused)."""
    if len(data) < HEADER_BYTES:
        raise MessageError(f"message of {len(data)} bytes: shorter than its {HEADER_BYTES}-byte header")
    magic, version, sender, timestamp, x, y, z, yaw, s_xy, s_z, s_yaw, count = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise MessageError(f"not a detection message (starts {magic!r}, expected {MAGIC!r})")
    if version not in DETECTIONS:
        raise MessageError(f"message format version {version}; this reader knows versions "
                           f"{', '.join(str(v) for v in DETECTIONS)}")
    if len(data) != message_bytes(count, version):
        raise MessageError(f"message of {len(data)} bytes for {count} version-{version} detections: expected "
                           f"{message_bytes(count, version)} (truncated or padded)")
    row = DETECTIONS[version]
    rows = np.array([row.unpack_from(data, HEADER_BYTES + k * row.size) for k in range(count)],
                    dtype=np.float64).reshape(-1, len(row.unpack(bytes(row.size))))
    header = np.array([timestamp, x, y, z, yaw, s_xy, s_z, s_yaw])
    if not (np.isfinite(header).all() and np.isfinite(rows).all()):
        raise MessageError("message holds a NaN or infinite value")
    _check_meaning(header, rows, version, num_classes)
    dets = WorldDetections(rows[:, 2:9], rows[:, 1], rows[:, 0].astype(np.int64))
    v, vc = (rows[:, 12:14], rows[:, 14:17]) if version >= 2 else (None, None)
    return CarMessage(sender, timestamp, (x, y, z, yaw), (s_xy, s_z, s_yaw), dets, rows[:, 9:12], v, vc)


def bounded_covariance(c) -> np.ndarray:
    """A (xx, xy, yy) covariance as a 2x2 matrix with its eigenvalues held between the floor and the ceiling
    (``COVARIANCE_FLOOR_M``, ``COVARIANCE_CEILING_M`` squared): positive definite, with a bounded weight."""
    m = np.array([[c[0], c[1]], [c[1], c[2]]], dtype=np.float64)
    values, vectors = np.linalg.eigh((m + m.T) / 2)
    values = np.clip(values, COVARIANCE_FLOOR_M ** 2, COVARIANCE_CEILING_M ** 2)
    return (vectors * values) @ vectors.T


def fuse_weighted(messages: list[CarMessage], radius: float, agreement: bool = False) -> WorldDetections:
    """The cars' detections, one per road user (``agreement.gather``): each group's centre is the average
    of its members' weighted by their inverse covariances (the noisier a sender's pose, the less its
    detection counts, each covariance held between a floor and a ceiling: ``bounded_covariance``, so no sender's
    weight is unbounded and the centre stays among the group's); the rest of the box is the best-scoring one's,
    and so is the score, or with
    ``agreement`` the noisy-OR of the senders in the group (``agreement.noisy_or``)."""
    dets = WorldDetections.concat([m.detections for m in messages]) if messages else WorldDetections.empty()
    cov = np.concatenate([m.covariance() for m in messages]) if messages else np.zeros((0, 3))
    owners = np.concatenate([np.full(len(m.detections), m.sender, np.int64) for m in messages]) if messages \
        else np.zeros(0, np.int64)
    groups = gather(dets, radius)
    boxes, scores = [], []
    for i, group in groups:
        info = [np.linalg.inv(bounded_covariance(cov[j])) for j in group]
        box = dets.boxes[i].copy()
        box[:2] = np.linalg.solve(sum(info), sum(w @ dets.boxes[j, :2] for w, j in zip(info, group)))
        boxes.append(box)
        scores.append(noisy_or(dets.scores[group], owners[group]) if agreement else dets.scores[i])
    k = np.asarray([i for i, _ in groups], dtype=np.int64)
    return WorldDetections(np.asarray(boxes, dtype=np.float64).reshape(-1, 7), np.asarray(scores, np.float64),
                           dets.classes[k])
