"""The cooperative setting's pose error: what each fusion survives when the other cars' poses are wrong.

    noise = PoseNoise(0.2, 0.2, seed=0)                # sigma metres (x, y, z), sigma degrees (yaw)
    seen_by_v = noise.item_for_target(item, v)         # the item as view v's car knows it
    moved = noise.boxes_from(item, v, world_boxes)     # a car's 3D detections as another car places them

As in OpenCOOD / V2X-ViT (FACTS.md): every car other than the target's own gets Gaussian noise on
x, y, z and on yaw of its pose, the same for all of that car's cameras; the target car's cameras,
the ground truth and every image stay exact. A car's error is drawn from the seed, the scenario and
the car alone, so runs repeat and a car has one error per frame whichever item it appears in. The
yaw error turns the car about its own centre (its 3D box; a camera on no car about itself), so all
of a car's cameras and the detections it sends move as one rigid body (``perturb``).
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass, replace

import numpy as np
import torch

from pnyolo.data.item import Item


def car_of(item: Item, v: int):
    """The car carrying view ``v``'s camera (its camera name when it is on no car)."""
    mounted = item.cameras[v].mounted_on
    return mounted if mounted is not None else f"camera {item.camera_names[v]}"


def _rz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def move_points(points: np.ndarray, offset: np.ndarray, yaw: float, pivot: np.ndarray) -> np.ndarray:
    """Points (..., 3) turned by ``yaw`` radians about the vertical through ``pivot`` (3,), then moved
    by ``offset`` (3,) metres: a car's pose error as a rigid motion."""
    return (np.asarray(points, dtype=np.float64) - pivot) @ _rz(yaw).T + pivot + offset


def perturb(camera_to_world: np.ndarray, offset: np.ndarray, yaw: float, pivot: np.ndarray) -> np.ndarray:
    """``camera_to_world`` (4, 4) moved by a pose error (``move_points``)."""
    out = np.array(camera_to_world, dtype=np.float64, copy=True)
    out[:3, :3] = _rz(yaw) @ out[:3, :3]
    out[:3, 3] = move_points(out[:3, 3], offset, yaw, pivot)
    return out


def pivot_of(item: Item, v: int) -> np.ndarray:
    """The point a car's yaw error turns it about: the centre of its 3D box, or the camera itself."""
    mounted = item.cameras[v].mounted_on
    ids = list(item.actor_ids)
    if mounted is not None and mounted in ids:
        return np.asarray(item.boxes_3d[ids.index(mounted)][:3], dtype=np.float64)
    return item.camera_to_world[v].double().numpy()[:3, 3]


@dataclass(frozen=True)
class PoseNoise:
    sigma_m: float
    sigma_deg: float
    seed: int = 0

    @property
    def active(self) -> bool:
        return self.sigma_m > 0 or self.sigma_deg > 0

    def error(self, item: Item, car) -> tuple[np.ndarray, float]:
        """(offset (3,) metres, yaw radians) of ``car``'s pose in ``item``'s scenario."""
        key = zlib.crc32(f"{self.seed}/{item.scenario}/{car}".encode())
        rng = np.random.default_rng(key)
        return rng.normal(0.0, self.sigma_m, 3), float(np.radians(rng.normal(0.0, self.sigma_deg)))

    def item_for_target(self, item: Item, target: int) -> Item:
        """``item`` with the cameras of every car but view ``target``'s perturbed (a shallow copy)."""
        if not self.active:
            return item
        own = car_of(item, target)
        c2w = item.camera_to_world.clone()
        for v in range(c2w.shape[0]):
            car = car_of(item, v)
            if car != own:
                offset, yaw = self.error(item, car)
                c2w[v] = torch.as_tensor(perturb(c2w[v].double().numpy(), offset, yaw, pivot_of(item, v)),
                                         dtype=c2w.dtype)
        return replace(item, camera_to_world=c2w)

    def boxes_from(self, item: Item, sender: int, boxes: np.ndarray, receiver: int) -> np.ndarray:
        """World boxes (P, 7) [cx, cy, cz, l, w, h, yaw] that view ``sender``'s car detected, as view
        ``receiver``'s car places them: moved by the sender's pose error (none from its own car)."""
        boxes = np.array(boxes, dtype=np.float64, copy=True).reshape(-1, 7)
        car = car_of(item, sender)
        if not self.active or car == car_of(item, receiver) or not len(boxes):
            return boxes
        offset, yaw = self.error(item, car)
        boxes[:, :3] = move_points(boxes[:, :3], offset, yaw, pivot_of(item, sender))
        boxes[:, 6] += yaw
        return boxes


def parse_pose_noise(text: str | None, seed: int = 0) -> PoseNoise | None:
    """``--pose-noise SIGMA_M,SIGMA_DEG`` -> ``PoseNoise`` (one-line errors for anything else)."""
    from dataset_spec.cli_support import UserError

    if text is None:
        return None
    try:
        sigma_m, sigma_deg = (float(v) for v in text.split(","))
    except ValueError:
        raise UserError(f"--pose-noise {text!r}: expected SIGMA_M,SIGMA_DEG, e.g. 0.2,0.2") from None
    if not (sigma_m >= 0 and sigma_deg >= 0) or not np.isfinite([sigma_m, sigma_deg]).all():
        raise UserError(f"--pose-noise {text!r}: sigmas must be finite and >= 0")
    return PoseNoise(sigma_m, sigma_deg, seed)


def training_poses(item: Item, sigmas: list[float] | None, step: int, rank: int = 0) -> Item:
    """``train.pose_noise`` [SIGMA_M, SIGMA_DEG]: the item with every car's pose but one (the step's
    ego, taking turns) wrong, fresh errors each step, seeded by the step so a resumed run repeats them."""
    if not sigmas:
        return item
    noise = PoseNoise(float(sigmas[0]), float(sigmas[1]), seed=step * 1009 + rank)
    return noise.item_for_target(item, step % len(item.camera_names))
