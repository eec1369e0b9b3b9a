"""Late fusion: each car detects on its own camera alone and sends its 3D detections; the detections
of every car are pooled in the world frame (one per road user: same-class centres closer than
``eval.centre_nms_m`` merged, the higher score kept) and projected into each target view. A pure function of
the messages: the models ran before (``pnyolo.engine.predict``), the cars' own detections are data
(``senders.OwnViews``).

    rule = LateRule.of(cfg.eval)                        # send / keep thresholds, calibration, radius
    messages = cars.messages(item, rule.send)           # each view's car's CarMessage (senders.OwnViews)
    dets = late_fusion(messages, item, rule)            # ViewDetections per view
    sent = sent_bytes(messages)                         # what the cars sent

A car sends a ``pnyolo.cooperation.message`` (48 bytes of header, 68 a detection), against the
encoder feature maps that the multi-view models read from its camera (``Model.feature_bytes``). With
pose noise each receiving car places the others' detections by their wrong poses and merges them
weighted by the covariance their messages state (``message.fuse_weighted``); with exact poses the
best-scoring detection of each road user is kept. With ``eval.late_keep`` set (the benchmark chooses
it on validation) the rule is agreement (``pnyolo.cooperation.agreement``): cars send from
``eval.late_send`` on, and a road user's reports are scored together by noisy-OR and kept from
``late_keep`` on, so what one car alone half-believes goes and what several cars see stays. With
``eval.late_calibration`` each received score is first replaced by the chance, fitted on validation, that
a report of that score at that distance from its sender is a road user (``pnyolo.cooperation.calibration``).
With an ``Ego`` each target view's car keeps its own detector's detections (the single view, say) and adds
the road users the other cars report (pooled by the best car, projected into the view) where it has no box.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from dataset_spec.boxes import box_iou
from dataset_spec.cli_support import UserError
from pnyolo.config import EvalConfig
from pnyolo.cooperation.agreement import fuse_agreeing
from pnyolo.cooperation.calibration import calibrated
from pnyolo.cooperation.message import CarMessage, fuse_weighted, message_bytes
from pnyolo.cooperation.pose_noise import car_of, pivot_of
from pnyolo.data.item import Item
from pnyolo.decoding.detections import ViewDetections, union
from pnyolo.decoding.world import WorldDetections, pool_views, project_into_views
from pnyolo.models.base import Decoding
from pnyolo.registry import kinds


def check_late_fusion(decoding: Decoding, need: str = "--late-fusion") -> None:
    """One-line error for a model (its ``Decoding``) without 3D detections (``need``: what asked for them)."""
    if not decoding.world_outputs:
        with_3d = " | ".join(k for k, cls in kinds().items() if cls.world_outputs)
        why = " trained without a 3D state (model.loss.state 0)" if decoding.kind_world_outputs else ""
        raise UserError(f"{need} needs a model with 3D detections (model.kind {with_3d}), not {decoding.kind}{why}")


@dataclass(frozen=True)
class Ego:
    """A receiving car that keeps its own detector: each target view's detections of the ``detections``
    (the ego model's, per view) scoring at least ``threshold``, and the other cars' reports that overlap
    none of them by more than IoU ``nms_iou`` (``add_reports``)."""

    detections: list
    threshold: float
    nms_iou: float


@dataclass(frozen=True)
class LateRule:
    """How the receiving cars pool: cars send from ``send``; the best car's detection of a road user kept
    (``keep`` None) or the reports scored together by agreement and kept from ``keep`` on, each score first
    ``calibration``-ed (agreement only); reports of one road user within ``radius`` metres."""

    send: float
    keep: float | None = None
    calibration: tuple | None = None
    radius: float = 1.0

    @classmethod
    def of(cls, ev: EvalConfig, send: float | None = None) -> "LateRule":
        """The rule ``ev`` states (``send``: instead, the best car's rule with the cars sending from there)."""
        if send is not None:
            return cls(send, None, None, ev.centre_nms_m)
        keep = ev.late_keep
        return cls(send_threshold(ev), keep, None if keep is None else ev.late_calibration, ev.centre_nms_m)


@dataclass(frozen=True)
class Channel:
    """What lies between the cars: ``pose_noise``, a ``PoseNoise`` by which each receiving car places the others'
    detections (None: exact poses). A message late to its receiver is moved to the receiver's time by the
    velocities it carries (message format 2; ``CarMessage.at``)."""

    pose_noise: object = None

    @property
    def noisy(self) -> bool:
        return self.pose_noise is not None and self.pose_noise.active


def sent_bytes(messages: list[CarMessage]) -> int:
    """The bytes the cars' ``messages`` take (``message.message_bytes``)."""
    return sum(message_bytes(len(m.detections)) for m in messages)


def late_fusion(messages: list[CarMessage], item: Item, rule: LateRule, channel: Channel = Channel(),
                ego: Ego | None = None) -> list[ViewDetections]:
    """Every view's detections after pooling the ``messages`` (each view's car's own 3D detections, sent from
    ``rule.send``; ``senders.OwnViews.messages``): each moved to the item's time -> what each receiver gets
    through the ``channel`` -> pooled by the ``rule`` -> merged into the ``ego`` if any (each target view's car
    keeps its own detector's detections and pools only the other cars' reports into them)."""
    now = item.frame / (item.fps or 1.0)
    cars = [m.detections if m.timestamp == now else m.at(now).detections for m in messages]
    cars = calibrated(cars, item, rule.calibration)  # as agreement weighs them
    if not channel.noisy and ego is None:  # every receiver gets the same: one pool for all views
        owners = [car_id(item, b) for b in range(len(cars))]
        return project_into_views(pool_cars(cars, owners, rule.radius, rule.keep), item, item.scored)
    fused = project_into_views(WorldDetections.empty(), item, [])  # every view empty until placed
    for v in item.scored:  # as view v's car places and weighs what the others sent
        pooled = received_pool(item, cars, v, channel.pose_noise if channel.noisy else None, rule.radius, rule.keep,
                               others_only=ego is not None)
        fused[v] = project_into_views(pooled, item, [v])[v]
        if ego is not None:
            fused[v] = add_reports(ego.detections[v].above(ego.threshold), fused[v], ego.nms_iou)
    return fused


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
    if keep is None:
        return pool_views(cars, radius)
    dets = WorldDetections.concat(cars) if cars else WorldDetections.empty()
    return fuse_agreeing(dets, np.repeat(np.asarray(owners, np.int64), [len(c) for c in cars]), radius).above(keep)


def add_reports(own: ViewDetections, reports: ViewDetections, nms_iou: float) -> ViewDetections:
    """``own`` with each of ``reports`` (other road users, already one each) whose box overlaps none of
    ``own``'s by more than ``nms_iou``: neither side's boxes suppress their own side's, so a reported road
    user hidden behind another report survives (class-agnostic)."""
    if len(own.boxes) and len(reports.boxes):
        reports = reports.take(box_iou(reports.boxes, own.boxes).max(axis=1) <= nms_iou)
    return union(own, reports)
