"""What the cars send, as data: every camera's own-view 3D detections by frame (``OwnViews``, from one own-view
``Predictions``) and, for a message late to its receiver, the velocities its sender's own tracker gives them
(message format 2): the messages and the tracks that move them come from the same predictions.

    cars = OwnViews(own_preds, cfg.eval)         # own_preds: predict(..., Condition(own_view=True))
    messages = cars.messages(item, 0.3)          # per view, its car's CarMessage from 0.3 on (late ones with velocities)
"""
from __future__ import annotations

import numpy as np

from dataset_spec.cli_support import UserError
from pnyolo.cooperation.late_fusion import car_id
from pnyolo.cooperation.message import CarMessage
from pnyolo.decoding.detections import WorldDetections
from pnyolo.decoding.ground_tracker import EVERY_DETECTION, GroundTracker


def sent_frame(item, b: int) -> int:
    """The frame view ``b``'s image and pose are of (the item's own without a delay)."""
    return item.view_frames[b] if item.view_frames else item.frame


def seconds(item, frame: int) -> float:
    """The time of ``frame`` of the item's sequence (one frame: its number)."""
    return frame / (item.fps or 1.0)


def sent_key(item, camera: int, frame: int | None) -> tuple:
    """(scenario, lighting variant, camera group, camera, frame): where a camera's own-view detections are kept."""
    return item.scenario, item.variant, tuple(item.views), camera, frame


class OwnViews:
    """Each camera's own-view outputs by (scenario, lighting variant, camera group, camera, frame), from ``preds``
    (one own-view ``Predictions``): a camera's own view is decoded on its group's grid (a ground-plane model's
    grid covers the group's sight), so a message is keyed by the group of the item it is sent in, at the frame
    its image is of; its 3D detections decoded under ``ev`` once per score threshold, and each camera's own
    tracker over them (``GroundTracker``)."""

    def __init__(self, preds, ev):
        self.preds, self.ev = preds, ev
        self.index: dict[tuple, tuple[int, int]] = {}
        for k, p in enumerate(preds.items):
            for b, camera in enumerate(p.item.views):
                self.index.setdefault(sent_key(p.item, camera, sent_frame(p.item, b)), (k, b))
        self._world: dict[tuple[int, float], list] = {}
        self._tracks: dict[tuple, tuple[GroundTracker, list]] = {}  # per camera and threshold

    def detections(self, key: tuple, threshold: float) -> WorldDetections:
        """The 3D detections of ``key`` = (scenario, variant, camera group, camera, frame) from ``threshold`` on."""
        if key not in self.index:
            raise UserError(f"no own-view detections of camera {key[3]} of {key[0]} ({key[1]}) at frame {key[4]} in "
                            f"the group of cameras {list(key[2])}: the cars' detections come from a dataset without it")
        k, b = self.index[key]
        if (k, threshold) not in self._world:
            self._world[(k, threshold)] = self.preds.world_at(k, self.ev, threshold)
        return self._world[(k, threshold)][b]

    def messages(self, item, threshold: float) -> list[CarMessage]:
        """What each view's car of ``item`` sends: its detections of the frame its image is of, from
        ``threshold``; a message older than the item's frame also with the velocities its own tracker gives them."""
        out = []
        for b, camera in enumerate(item.views):
            frame = sent_frame(item, b)
            dets = self.detections(sent_key(item, camera, frame), threshold)
            v, vc = self.velocities(item, b, threshold) if frame != item.frame and len(dets) else (None, None)
            out.append(CarMessage(car_id(item, b), seconds(item, frame), (0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), dets,
                                  velocities=v, velocity_covariances=vc))
        return out

    def velocities(self, item, b: int, threshold: float) -> tuple[np.ndarray, np.ndarray]:
        """(P, 2) ground velocities and (P, 3) their covariances (xx, xy, yy) of what view ``b``'s car sends from
        the frame its image is of, as that car's own tracker estimates them from its own detections."""
        key = (sent_key(item, item.views[b], None), threshold)
        if key not in self._tracks:
            self._tracks[key] = (GroundTracker(item.fps or 1.0, EVERY_DETECTION), [])  # what it sends, it believes
        tracker, tracks = self._tracks[key]
        for f in range(len(tracks), sent_frame(item, b) + 1):  # the sender's own past, then the frame it sends
            steps = tracker.step(f, self.detections(sent_key(item, item.views[b], f), threshold))
            tracks.append((np.array([s[2:] for s, _ in steps]).reshape(-1, 2),
                           np.array([[c[2, 2], c[2, 3], c[3, 3]] for _, c in steps]).reshape(-1, 3)))
        return tracks[sent_frame(item, b)]
