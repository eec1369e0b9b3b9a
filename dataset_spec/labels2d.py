"""2D label records: one actor as one camera sees it (``Label2D``), the thresholds that select ground truth
(``LabelThresholds``) and a view's labels (``ViewLabels``, the ``labels.json`` of SPEC.md section 6),
with strict JSON (de)serialisation like the other records (``dataset_spec.schema``)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .names import excerpt
from .schema import KITTI_OCCLUSION_LEVELS, SPEC_VERSION, SUPPORTED_VERSIONS, Fields, extras_of


@dataclass
class Label2D:
    """One actor as seen by one camera (written by the projection tool)."""

    instance_id: int
    cls: str
    box: np.ndarray  # amodal [x0, y0, x1, y1], clipped to the image, spec pixel coords
    in_frame_fraction: float  # share of the 3D box inside the view frustum (1 - truncation)
    # visible pixels / in-image amodal silhouette pixels (1 - occlusion); None: not measured (no instance maps)
    visible_fraction: float | None
    distance: float  # metres from the camera centre to the box centre
    visible_pixels: int | None = 0  # None with visible_fraction None
    amodal_pixels: int | None = 0  # silhouette pixels inside the image
    occlusion_level: int = 3  # KITTI: 0 visible, 1 partly, 2 largely occluded, 3 unknown
    extras: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"instance_id": self.instance_id, "class": self.cls, "box": np.asarray(self.box, float).tolist(),
                "in_frame_fraction": self.in_frame_fraction, "visible_fraction": self.visible_fraction,
                "distance": self.distance, "visible_pixels": self.visible_pixels, "amodal_pixels": self.amodal_pixels,
                "occlusion_level": self.occlusion_level, "extras": self.extras}

    @classmethod
    def from_fields(cls, f: Fields) -> "Label2D":
        label = cls(f.get("instance_id", int), f.get("class", str), f.array("box", (4,)),
                    f.get("in_frame_fraction", float), f.get("visible_fraction", float, allow_none=True),
                    f.get("distance", float), f.get("visible_pixels", int, 0, allow_none=True),
                    f.get("amodal_pixels", int, 0, allow_none=True), f.get("occlusion_level", int, 3), extras_of(f))
        for key in ("in_frame_fraction", "visible_fraction"):
            value = getattr(label, key)
            if value is not None and not 0.0 <= value <= 1.0 + 1e-6:
                raise f.err(key, "must be within [0, 1]")
        if label.box[2] < label.box[0] or label.box[3] < label.box[1]:
            raise f.err("box", "x1 < x0 or y1 < y0")
        if label.occlusion_level not in KITTI_OCCLUSION_LEVELS:
            raise f.err("occlusion_level", "must be 0, 1, 2 or 3")
        return label


@dataclass
class LabelThresholds:
    """Which labels count as ground truth. Stored with the labels; re-applicable later."""

    min_in_frame: float = 0.25
    min_visible: float = 0.0
    max_distance: float | None = None
    min_box_pixels: float = 2.0  # minimum width and height of the clipped box
    per_class: dict[str, dict[str, float]] = field(default_factory=dict)  # {"pedestrian": {"max_distance": 40}}

    def for_class(self, cls: str) -> "LabelThresholds":
        over = self.per_class.get(cls, {})
        return LabelThresholds(**{**{k: getattr(self, k) for k in ("min_in_frame", "min_visible", "max_distance",
                                                                   "min_box_pixels")}, **over})

    def accepts(self, label: Label2D) -> bool:
        t = self.for_class(label.cls)
        w, h = label.box[2] - label.box[0], label.box[3] - label.box[1]
        visible = label.visible_fraction is None or label.visible_fraction >= t.min_visible  # unknown: not judged
        return (label.in_frame_fraction >= t.min_in_frame and visible
                and (t.max_distance is None or label.distance <= t.max_distance)
                and min(w, h) >= t.min_box_pixels)

    def to_dict(self) -> dict:
        return {"min_in_frame": self.min_in_frame, "min_visible": self.min_visible, "max_distance": self.max_distance,
                "min_box_pixels": self.min_box_pixels, "per_class": self.per_class}

    @classmethod
    def from_fields(cls, f: Fields) -> "LabelThresholds":
        allowed = {"min_in_frame", "min_visible", "max_distance", "min_box_pixels"}
        per_class = f.get("per_class", dict, {})
        for name, over in per_class.items():
            if not isinstance(over, dict) or not set(over) <= allowed:
                raise f.err("per_class", f"class {excerpt(name)}: options must be among {sorted(allowed)}")
        return cls(f.get("min_in_frame", float, 0.25), f.get("min_visible", float, 0.0),
                   f.get("max_distance", float, None, allow_none=True), f.get("min_box_pixels", float, 2.0), per_class)


@dataclass
class ViewLabels:
    """All candidate labels of one camera, plus the thresholds that select ground truth."""

    scenario: str
    camera: str
    width: int
    height: int
    thresholds: LabelThresholds
    objects: list[Label2D]
    frame: int = 0  # the frame of a sequence they label (1.2)

    def kept(self, thresholds: LabelThresholds | None = None) -> list[Label2D]:
        t = thresholds or self.thresholds
        return [o for o in self.objects if t.accepts(o)]

    def left_out(self, thresholds: LabelThresholds | None = None) -> list[Label2D]:
        """The labels the thresholds reject: real road users outside the ground truth (ignore regions)."""
        t = thresholds or self.thresholds
        return [o for o in self.objects if not t.accepts(o)]

    def to_dict(self) -> dict:
        return {"spec_version": SPEC_VERSION, "scenario": self.scenario, "camera": self.camera,
                **({"frame": self.frame} if self.frame else {}), "width": self.width, "height": self.height,
                "thresholds": self.thresholds.to_dict(), "objects": [o.to_dict() for o in self.objects]}

    @classmethod
    def from_dict(cls, obj: Any, path=None) -> "ViewLabels":
        f = Fields(obj, path)
        if f.get("spec_version", str) not in SUPPORTED_VERSIONS:
            raise f.err("spec_version", "unsupported version")
        frame = f.get("frame", int, 0)
        if frame < 0:
            raise f.err("frame", "must be >= 0")
        return cls(f.name("scenario"), f.name("camera"), f.get("width", int), f.get("height", int),
                   LabelThresholds.from_fields(f.sub("thresholds")), [Label2D.from_fields(o) for o in f.items("objects")],
                   frame)
