"""Where a trained model runs outside training: each (model, split, condition) predicted once and kept as a
``Predictions`` value that every analysis reads (the validation sweeps, late fusion, the test metrics, the
pose-noise and delay sweeps, tracking, coverage, pnyolo-eval, -predict and -track), never running a model itself
(MMDetection3D's ``model.predict`` -> data samples -> ``metric.process``)::

    preds = predict(model, dataset, cfg.eval)                                  # clean: every item's outputs
    own = predict(model, dataset, cfg.eval, Condition(own_view=True))          # every view alone
    noisy = predict(model, dataset, cfg.eval, Condition(pose_noise=noise))     # each scored view as its car knows
    preds.detections(cfg.eval)      # per item, each view's detections under those settings (threshold, NMS, peaks)
    preds.world_at(0, cfg.eval, 0.3)  # item 0's 3D detections per view from that score (world-output kinds)
    preds.decoding                  # the kind's decoding (pnyolo.models.Decoding): what an analysis gets, not the model

A condition is what the model sees: the clean item, each view alone (``own_view``: the own-view ablation and the
cars' own detections late fusion pools), the other cars' poses wrong (``pose_noise``: one pass per scored view,
as that view's car places the others). A delay is a dataset of its own (``Delay``), predicted the same way. The
outputs are kept at the most depth peaks asked for (``Condition.peaks``): decoding with fewer takes the first of
them, which a pass with fewer would have made (``RayOutputs.first_peaks``). Items are kept without their images
(an analysis that draws one loads it again from the dataset).
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from pnyolo.components.backbones import backbone_computed
from pnyolo.config import Config
from pnyolo.data.item import Item
from pnyolo.models import Decoding, Model, predict_item
from pnyolo.models.base import Outputs


@dataclass(frozen=True)
class Trained:
    """A trained model and the config it was loaded with (``path``: the checkpoint it came from, if any); what
    runs it is ``predict``, what reads it is its ``decoding``."""

    path: Path | None
    model: Model
    config: Config

    @property
    def decoding(self) -> Decoding:
        return Decoding.of(self.model)


@dataclass(frozen=True)
class Condition:
    """What the model sees of an item (the module docstring); ``samples``: keep the samples a kind that says
    where it queries the world queried (coverage); ``peaks``: depth peaks to keep (None: the settings')."""

    own_view: bool = False
    pose_noise: object = None  # pnyolo.cooperation.pose_noise.PoseNoise; None: exact poses
    samples: bool = False
    peaks: int | None = None

    @property
    def noisy(self) -> bool:
        return self.pose_noise is not None and self.pose_noise.active


@dataclass
class Predicted:
    """One item's outputs: ``out`` the pass on the item, or under pose noise ``per_view`` the pass of each scored
    view as its car knows the others (view position -> (the item as that car sees it, outputs))."""

    item: Item
    out: Outputs = None
    per_view: dict[int, tuple[Item, Outputs]] | None = None


@dataclass
class Predictions:
    """A model's outputs on a dataset's items under one condition, ``items[k]`` of the dataset's item ``k``, and
    the kind's ``decoding`` that reads them (no model: an analysis cannot run one)."""

    decoding: Decoding
    condition: Condition
    items: list[Predicted] = field(default_factory=list)
    keys: list = field(default_factory=list)  # each item's dataset key (``MultiViewDataset.items``)

    def __len__(self) -> int:
        return len(self.items)

    def detections_at(self, k: int, ev, threshold: float | None = None) -> list:
        """Item ``k``'s detections per view decoded under ``ev`` (``threshold``: instead of its confidence
        threshold); under pose noise each scored view from its own pass, the others from the last one."""
        p = self.items[k]
        if p.per_view is None:
            return self.decoding.decode(p.out, p.item, ev, threshold)
        dets = None
        for v, (seen, out) in p.per_view.items():
            per = self.decoding.decode(out, seen, ev, threshold)
            dets = per if dets is None else [per[u] if u == v else d for u, d in enumerate(dets)]
        return dets

    def detections(self, ev, threshold: float | None = None) -> list[list]:
        """``detections_at`` of every item."""
        return [self.detections_at(k, ev, threshold) for k in range(len(self.items))]

    def world_at(self, k: int, ev, threshold: float) -> list:
        """Item ``k``'s 3D detections per view from ``threshold`` on (a world-output kind's)."""
        return self.decoding.world_detections(self.items[k].out, self.items[k].item, ev, threshold)

    def on(self, dataset) -> "Predictions":
        """These predictions of ``dataset``'s items, in its order (a dataset of a subset of the items predicted:
        another lighting or a later first frame); KeyError for an item not predicted."""
        where = {_key(k): i for i, k in enumerate(self.keys)}
        chosen = [where[_key(k)] for k in dataset.items]
        return Predictions(self.decoding, self.condition, [self.items[i] for i in chosen], [self.keys[i] for i in chosen])


def _key(key) -> tuple:
    """A dataset item key as a hashable tuple (its camera group's lists as tuples)."""
    return tuple(tuple(map(tuple, v)) if isinstance(v, tuple) and v and isinstance(v[0], list) else v for v in key)


def _light(item):
    """``item`` without its images (what no analysis of outputs reads; pictures load the item again)."""
    return replace(item, images=None, surface_depth=None)


@torch.no_grad()
def predict(model: Model, dataset, ev, condition: Condition = Condition(), device=None, runner=None,
            progress: bool = False, constants=None) -> Predictions:
    """``model`` on every item of ``dataset`` under ``condition``, in evaluation mode (restored after);
    ``runner`` computes the outputs instead of torch (an ONNX Runtime runner); ``constants``: item -> the
    rig's precomputed constants (``inference.RigConstants``) to pass to the model."""
    ev = ev if condition.peaks is None else replace(ev, depth_peaks=condition.peaks)
    was = model.training
    model.eval()
    found = Predictions(Decoding.of(model), condition, keys=list(getattr(dataset, "items", range(len(dataset)))))
    for k in tqdm(range(len(dataset)), desc="predicting", unit="item", disable=not progress, file=sys.stderr):
        item = dataset[k]
        if condition.noisy and item.scored:
            seen = {v: condition.pose_noise.item_for_target(item, v) for v in item.scored}
            found.items.append(Predicted(_light(item), per_view={
                v: (_light(s), predict_item(model, s, device, ev)) for v, s in seen.items()}))
            continue
        options = {"own_view_only": condition.own_view,
                   "return_samples": condition.samples and bool(model.coverage_text), **(constants(item) if constants else {})}
        out = runner(item) if runner is not None else predict_item(model, item, device, ev, **options)
        found.items.append(Predicted(_light(item), out))
    model.train(was)
    return found


@torch.no_grad()
def time_per_item(model, dataset, ev, items: int = 12) -> float:
    """Milliseconds per item (a frame of data.num_views views): forward pass and decoding, the model in
    evaluation mode (the backbone run, not read from a feature cache), the median of ``items`` items after one
    warm-up."""
    was = model.training
    model.eval()
    times = []
    with backbone_computed(model):
        for k in range(min(items, len(dataset)) + 1):
            item = dataset[k % len(dataset)]
            t = time.perf_counter()
            model.decode(predict_item(model, item, None, ev), item, ev)
            times.append(time.perf_counter() - t)
    model.train(was)
    return float(np.median(times[1:]) * 1000)
