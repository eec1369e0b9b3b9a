"""Late fusion: each car detects on its own camera alone and sends its 3D detections; the detections
of every car are pooled in the world frame (one per road user: same-class centres closer than
``eval.centre_nms_m`` merged, the higher score kept) and projected into each target view.

    dets, sent = late_fusion(bev_model, item, None, cfg.eval)   # ViewDetections per view, bytes sent

A car sends a ``pnyolo.evaluation.message`` (48 bytes of header, 68 a detection), against the
encoder feature maps that the multi-view models read from its camera (``Model.feature_bytes``). With
pose noise each receiving car places the others' detections by their wrong poses and merges them
weighted by the covariance their messages state (``message.fuse_weighted``); with exact poses the
best-scoring detection of each road user is kept. With ``eval.late_keep`` set (the benchmark chooses
it on validation) the rule is agreement (``pnyolo.evaluation.agreement``): cars send from
``eval.late_send`` on, and a road user's reports are scored together by noisy-OR and kept from
``late_keep`` on, so what one car alone half-believes goes and what several cars see stays. With
``eval.late_calibration`` each received score is first replaced by the chance, fitted on validation, that
a report of that score at that distance from its sender is a road user (``pnyolo.evaluation.calibration``).
With an ``Ego`` each target view's car keeps its own detector's detections (the single view, say) and adds
the road users the other cars report (pooled by the best car, projected into the view) where it has no box.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
import torch

from dataset_spec.cli_support import UserError
from pnyolo.config import EvalConfig
from pnyolo.data.item import Item
from pnyolo.evaluation.metrics import ViewDetections
from pnyolo.evaluation.agreement import fuse_agreeing
from pnyolo.evaluation.calibration import calibrated
from pnyolo.evaluation.fusion import add_reports
from pnyolo.evaluation.message import CarMessage, fuse_weighted, message_bytes
from pnyolo.evaluation.pose_noise import car_of, pivot_of
from pnyolo.decoding.world import WorldDetections, centre_nms, project_into_views
from pnyolo.models import predict_item
from pnyolo.registry import kinds


def check_late_fusion(model, need: str = "--late-fusion") -> None:
    """One-line error for a model without 3D detections (``need``: what asked for them)."""
    if not model.world_outputs:
        with_3d = " | ".join(k for k, cls in kinds().items() if cls.world_outputs)
        raise UserError(f"{need} needs a model with 3D detections (model.kind {with_3d}), not {model.kind}")


@dataclass(frozen=True)
class Ego:
    """A receiving car that keeps its own detector: each target view's detections of the ``detections``
    (the ego model's, per view) scoring at least ``threshold``, and the other cars' reports that overlap
    none of them by more than IoU ``nms_iou`` (``fusion.add_reports``)."""

    detections: list
    threshold: float
    nms_iou: float


@dataclass(frozen=True)
class Channel:
    """What lies between the cars: ``pose_noise``, a ``PoseNoise`` by which each receiving car places the others'
    detections (None: exact poses); ``senders``, a ``pnyolo.tracking.senders.SenderTracks`` by whose velocities a
    late car's detections are moved to the item's frame (message format 2; None: they stand where that car saw
    them)."""

    pose_noise: object = None
    senders: object = None

    @property
    def noisy(self) -> bool:
        return self.pose_noise is not None and self.pose_noise.active

    def to_now(self, model, ev: EvalConfig, threshold: float, item: Item, cars: list[WorldDetections]
               ) -> list[WorldDetections]:
        """Each view's car's detections as the receivers get them at the item's frame."""
        if self.senders is None or not item.view_frames:
            return cars
        return [_to_now(model, ev, threshold, item, b, c, self.senders) for b, c in enumerate(cars)]


@torch.no_grad()
def late_fusion(model, item: Item, device, ev: EvalConfig, threshold: float | None = None, own_view_out=None,
                channel: Channel = Channel(), ego: Ego | None = None) -> tuple[list[ViewDetections], int]:
    """Every view's detections after pooling each source view's own (``model`` run on each alone),
    and the bytes all cars sent (``threshold`` overrides ``ev.conf_threshold``; ``own_view_out``: the
    model's ``own_view_only`` outputs for ``item`` if already computed; ``channel``: pose noise and delay
    between the cars; ``ego``: each target view's car keeps its own detector's detections and pools only the
    other cars' reports into them). The steps: the cars' messages -> what each receiver gets through the
    channel -> pooled by the rule -> merged into the ego if any."""
    check_late_fusion(model)
    keep = ev.late_keep if threshold is None else None  # by agreement, unless a threshold overrides it
    t = send_threshold(ev) if threshold is None else threshold
    out = own_view_out if own_view_out is not None else predict_item(model, item, device, ev, own_view_only=True)
    cars = channel.to_now(model, ev, t, item, model.world_detections(out, ev, t))
    sent = sum(message_bytes(len(c)) for c in cars)
    cars = calibrated(cars, item, None if keep is None else ev.late_calibration)  # as agreement weighs them
    if not channel.noisy and ego is None:  # every receiver gets the same: one pool for all views
        owners = [car_id(item, b) for b in range(len(cars))]
        return project_into_views(pool_cars(cars, owners, ev.centre_nms_m, keep), item, item.scored), sent
    fused = project_into_views(WorldDetections.empty(), item, [])  # every view empty until placed
    for v in item.scored:  # as view v's car places and weighs what the others sent
        pooled = received_pool(item, cars, v, channel.pose_noise if channel.noisy else None, ev.centre_nms_m, keep,
                               others_only=ego is not None)
        fused[v] = project_into_views(pooled, item, [v])[v]
        if ego is not None:
            fused[v] = add_reports(ego.detections[v].above(ego.threshold), fused[v], ego.nms_iou)
    return fused, sent


def received_pool(item: Item, cars: list[WorldDetections], v: int, pose_noise, radius: float, keep: float | None,
                  others_only: bool = False) -> WorldDetections:
    """What view ``v``'s car makes of the cars' detections: each placed by the sender's pose as that car knows it
    (``pose_noise``: its error, the messages weighted by the covariance they state; None: exact, the best car or
    agreement), pooled within ``radius``; ``others_only``: its own car's left out (it keeps its own detector)."""
    others = [b for b in range(len(cars)) if not others_only or car_of(item, b) != car_of(item, v)]
    if pose_noise is None:
        return pool_cars([cars[b] for b in others], [car_id(item, b) for b in others], radius, keep)
    received = [car_message(item, b, WorldDetections(pose_noise.boxes_from(item, b, cars[b].boxes, v), cars[b].scores,
                                                     cars[b].classes), pose_noise, receiver=v) for b in others]
    pooled = fuse_weighted(received, radius, agreement=keep is not None)
    return pooled if keep is None else pooled.above(keep)


def _to_now(model, ev: EvalConfig, threshold: float, item: Item, b: int, dets: WorldDetections, senders
            ) -> WorldDetections:
    """View ``b``'s car's detections, from the frame its image is of, moved to the item's frame by the
    velocities its own tracker gives them (what a receiver does with a late message of format 2)."""
    if item.view_frames[b] == item.frame or not len(dets):
        return dets
    fps = senders.dataset.ds.scenario(item.scenario).fps or 1.0
    v, vc = senders.velocities(model, ev, threshold, item, b, dets)
    msg = CarMessage(0, item.view_frames[b] / fps, (0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), dets, velocities=v,
                     velocity_covariances=vc)
    return msg.at(item.frame / fps).detections


def car_message(item: Item, b: int, dets: WorldDetections, pose_noise=None, receiver: int | None = None) -> CarMessage:
    """View ``b``'s car's message: its pose (the car's centre and heading) and, under ``pose_noise``,
    that pose's uncertainty (none as its own ``receiver`` knows it)."""
    c2w = item.camera_to_world[b].double().numpy()
    x, y, z = pivot_of(item, b)
    heading = float(np.arctan2(c2w[1, 2], c2w[0, 2]))  # the camera's optical axis on the ground
    own = receiver is not None and car_of(item, receiver) == car_of(item, b)
    sigma = (0.0, 0.0, 0.0) if pose_noise is None or own else (pose_noise.sigma_m, pose_noise.sigma_m,
                                                               pose_noise.sigma_deg)
    return CarMessage(car_id(item, b), 0.0, (x, y, z, heading), sigma, dets)


def send_threshold(ev: EvalConfig) -> float:
    """The score from which a car sends a detection: ``eval.late_send``, or the model's ``eval.conf_threshold``."""
    return ev.late_send if ev.late_send is not None else ev.conf_threshold


def car_id(item: Item, b: int) -> int:
    """The sender id of the car carrying view ``b``'s camera (a message's ``sender``)."""
    return zlib.crc32(str(car_of(item, b)).encode())


def pool_cars(cars: list[WorldDetections], owners: list[int], radius: float, keep: float | None = None
              ) -> WorldDetections:
    """Several views' 3D detections (``cars``, each reported by the car ``owners`` names) pooled, one per
    road user within ``radius`` metres: the best-scoring kept (``keep`` None), or scored by the noisy-OR
    of the cars that reported it and kept from ``keep`` on (``agreement.fuse_agreeing``)."""
    dets = WorldDetections.concat(cars) if cars else WorldDetections.empty()
    if keep is None:
        return centre_nms(dets, radius)
    return fuse_agreeing(dets, np.repeat(np.asarray(owners, np.int64), [len(c) for c in cars]), radius).above(keep)
