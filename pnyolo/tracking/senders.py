"""What a car knows of the road users' motion when it sends a late message: its own tracker over its own
detections up to the frame it sends (``GroundTracker``), giving each detection it sends a velocity and
that velocity's covariance (message format 2).

    senders = SenderTracks(dataset)
    v, vcov = senders.velocities(model, cfg.eval, threshold, item, b, dets)   # (P, 2), (P, 3) of view b's car

Each car's own-view detections of its earlier frames are computed once (the model on that camera alone)
and kept for the next item that needs them.
"""
from __future__ import annotations

import numpy as np
import torch

from pnyolo.data.dataset import Draw
from pnyolo.decoding.detections import WorldDetections
from pnyolo.models import predict_item
from pnyolo.decoding.ground_tracker import GroundTracker


class SenderTracks:
    def __init__(self, dataset, device=None):
        self.dataset, self.device = dataset, device
        self._own: dict[tuple, WorldDetections] = {}

    @torch.no_grad()
    def _detections(self, model, ev, threshold: float, scenario: str, variant: str, camera: int, frame: int):
        key = (id(model), threshold, scenario, variant, camera, frame)
        if key not in self._own:
            item = self.dataset.load(scenario, variant, [camera], frame=frame, draw=Draw(mirror=False, shifts=[(0, 0)]))
            out = predict_item(model, item, self.device, ev, own_view_only=True)
            self._own[key] = model.world_detections(out, ev, threshold)[0]
        return self._own[key]

    def velocities(self, model, ev, threshold: float, item, b: int, dets: WorldDetections
                   ) -> tuple[np.ndarray, np.ndarray]:
        """(P, 2) ground velocities and (P, 3) their covariances (xx, xy, yy) of ``dets``, the detections view
        ``b``'s car sends from the frame its image is of, as that car's own tracker estimates them."""
        frame = item.view_frames[b] if item.view_frames else item.frame
        fps = self.dataset.ds.scenario(item.scenario).fps or 1.0
        tracker = GroundTracker(fps)
        for f in range(frame):  # the sender's own past
            tracker.step(f, self._detections(model, ev, threshold, item.scenario, item.variant, item.views[b], f))
        tracks = tracker.step(frame, dets)
        v = np.array([s[2:] for s, _ in tracks]).reshape(-1, 2)
        vc = np.array([[c[2, 2], c[2, 3], c[3, 3]] for _, c in tracks]).reshape(-1, 3)
        return v, vc
