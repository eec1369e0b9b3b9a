"""The message a car sends for late fusion: a versioned binary format (docs/guide/cooperation.md).

    msg = CarMessage(sender=7, timestamp=12.5, pose=(x, y, z, yaw), pose_sigma=(0.2, 0.2, 0.2), detections=dets)
    data = encode(msg)                    # 48 bytes of header + 48 bytes per detection
    back = decode(data)                   # MessageError (one line) for a wrong version, truncation, NaN

Little-endian. Header: magic ``PNYM``, version (uint16), sender id (uint32), timestamp (float64 s),
sender pose x, y, z (m), yaw (rad), its uncertainty sigma_xy, sigma_z (m), sigma_yaw (deg) (float32
each), detection count (uint16). Each detection: class (uint8, 3 pad bytes), score, centre x, y, z,
size length, width, height, yaw, position covariance xx, xy, yy on the ground plane (float32 each).
Values keep float32 precision (a relative error below 1e-7).
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from dataset_spec.cli_support import UserError
from pnyolo.decoding.world import WorldDetections

MAGIC = b"PNYM"
VERSION = 1
HEADER = struct.Struct("<4sHIdfffffffH")
DETECTION = struct.Struct("<B3xfffffffffff")
HEADER_BYTES, DETECTION_BYTES = HEADER.size, DETECTION.size


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

    def covariance(self) -> np.ndarray:
        return self.covariances if self.covariances is not None else position_covariance(
            self.detections.boxes, self.pose, self.pose_sigma)


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


def message_bytes(detections: int) -> int:
    """The size of a message carrying ``detections`` detections."""
    return HEADER_BYTES + detections * DETECTION_BYTES


def encode(msg: CarMessage) -> bytes:
    dets, cov = msg.detections, msg.covariance()
    out = [HEADER.pack(MAGIC, VERSION, msg.sender, msg.timestamp, *msg.pose, *msg.pose_sigma, len(dets))]
    for box, score, cls, c in zip(dets.boxes, dets.scores, dets.classes, cov):
        out.append(DETECTION.pack(int(cls), float(score), *(float(v) for v in box), *(float(v) for v in c)))
    return b"".join(out)


def decode(data: bytes) -> CarMessage:
    """The message in ``data`` (one-line ``MessageError`` for anything that is not a whole, finite
    message of this version)."""
    if len(data) < HEADER_BYTES:
        raise MessageError(f"message of {len(data)} bytes: shorter than its {HEADER_BYTES}-byte header")
    magic, version, sender, timestamp, x, y, z, yaw, s_xy, s_z, s_yaw, count = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise MessageError(f"not a detection message (starts {magic!r}, expected {MAGIC!r})")
    if version != VERSION:
        raise MessageError(f"message format version {version}; this reader knows version {VERSION}")
    if len(data) != message_bytes(count):
        raise MessageError(f"message of {len(data)} bytes for {count} detections: expected "
                           f"{message_bytes(count)} (truncated or padded)")
    rows = np.array([DETECTION.unpack_from(data, HEADER_BYTES + k * DETECTION_BYTES) for k in range(count)],
                    dtype=np.float64).reshape(-1, 12)
    header = np.array([timestamp, x, y, z, yaw, s_xy, s_z, s_yaw])
    if not (np.isfinite(header).all() and np.isfinite(rows).all()):
        raise MessageError("message holds a NaN or infinite value")
    dets = WorldDetections(rows[:, 2:9], rows[:, 1], rows[:, 0].astype(np.int64))
    return CarMessage(sender, timestamp, (x, y, z, yaw), (s_xy, s_z, s_yaw), dets, rows[:, 9:12])


def fuse_weighted(messages: list[CarMessage], radius: float) -> WorldDetections:
    """The cars' detections, one per road user: greedily by score, a detection gathers the not yet
    taken ones of its class within ``radius`` metres, and their centres are averaged weighted by
    their inverse covariances (the noisier a sender's pose, the less its detection counts); the rest
    of the box and the score are the best-scoring one's."""
    dets = WorldDetections.concat([m.detections for m in messages]) if messages else WorldDetections.empty()
    cov = np.concatenate([m.covariance() for m in messages]) if messages else np.zeros((0, 3))
    taken = np.zeros(len(dets), dtype=bool)
    boxes = []
    keep = []
    for i in np.argsort(-dets.scores, kind="stable"):
        if taken[i]:
            continue
        group = [j for j in range(len(dets)) if not taken[j] and dets.classes[j] == dets.classes[i]
                 and np.hypot(*(dets.boxes[j, :2] - dets.boxes[i, :2])) < radius]
        taken[group] = True
        info = [np.linalg.inv(np.array([[cov[j, 0], cov[j, 1]], [cov[j, 1], cov[j, 2]]])) for j in group]
        xy = np.linalg.solve(sum(info), sum(w @ dets.boxes[j, :2] for w, j in zip(info, group)))
        box = dets.boxes[i].copy()
        box[:2] = xy
        boxes.append(box)
        keep.append(i)
    k = np.asarray(keep, dtype=np.int64)
    return WorldDetections(np.asarray(boxes, dtype=np.float64).reshape(-1, 7), dets.scores[k], dets.classes[k])
