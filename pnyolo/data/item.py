"""One example as every model, loss, metric and picture reads it: the source views of one scene at one
frame under one lighting variant. Built by the dataset (``pnyolo.data.dataset``, with ground truth) and by the
inference API (``pnyolo.inference``, without)::

    item = dataset[0]
    item.images.shape           # (V, 3, H, W) float in [0, 1]
    item.K, item.camera_to_world  # (V, 3, 3) at the encoded size, (V, 4, 4) world metres
    model.targets(item)         # the kind's training targets, built from item.gt
    item.gt[v].boxes            # view v's ground truth (pixels of the encoded image)
    dataclasses.replace(item, camera_to_world=moved)   # the same item with other poses
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from torch import Tensor

from dataset_spec import LabelThresholds
from pnyolo.data.grid import GridSpec


@dataclass
class ViewCamera:
    """What putting a 3D box into a view needs beyond K and the pose (``pnyolo.decoding.world``)."""

    near: float  # clip planes, metres
    far: float
    size: tuple[int, int]  # the renders' (width, height): label thresholds count these pixels
    thresholds: LabelThresholds  # what a labelled road user, or a 3D detection put into the view, is held to
    mounted_on: int | None = None  # the actor (car) carrying the camera


@dataclass
class ViewGroundTruth:
    """One view's ground truth, in the pixels of the encoded image."""

    boxes: np.ndarray  # (G, 4)
    classes: np.ndarray  # (G,)
    visible_fraction: np.ndarray = field(default=None)  # (G,)
    seen_elsewhere: np.ndarray = field(default=None)  # (G,) bool: another source view sees it
    distances: np.ndarray | None = None
    # (K, 4) labelled road users left out of the ground truth by the label thresholds (too far,
    # too truncated): a prediction on one is ignored (strict mode), never a miss either.
    excluded_boxes: np.ndarray | None = None
    # (G,) the most visible pixels of the object in another source view (at the renders' resolution)
    other_view_pixels: np.ndarray | None = None
    centres: np.ndarray | None = None  # (G, 3) world centres of the 3D boxes
    world_boxes: np.ndarray | None = None  # (G, 7) their 3D boxes [cx, cy, cz, length, width, height, yaw]
    velocities: np.ndarray | None = None  # (G, 2) their ground velocities, m/s (NaN: not known, one frame)
    excluded_centres: np.ndarray | None = None  # (K, 3) those of the excluded road users
    excluded_classes: np.ndarray | None = None  # (K,) their classes (None: each excludes every class)
    object_rows: np.ndarray | None = None  # (G,) each road user's row in the item's boxes_3d
    excluded_rows: np.ndarray | None = None  # (K,) those of the excluded road users

    def __post_init__(self):
        g = len(self.boxes)
        if self.visible_fraction is None:
            self.visible_fraction = np.ones(g)
        if self.seen_elsewhere is None:
            self.seen_elsewhere = np.zeros(g, dtype=bool)



@dataclass
class Item:
    images: Tensor  # (V, 3, H, W) in [0, 1]
    K: Tensor  # (V, 3, 3) intrinsics of the encoded images
    camera_to_world: Tensor  # (V, 4, 4)
    grid: GridSpec  # the encoded size and YOLO grid
    cameras: list[ViewCamera]
    class_names: list[str]
    scored: list[int]  # positions of the views evaluation scores (the others are source views only)
    gt: list[ViewGroundTruth] = field(default_factory=list)  # per view (none without ground truth)
    boxes_3d: Tensor | None = None  # (N, 7) [cx, cy, cz, length, width, height, yaw] world metres
    velocities: Tensor | None = None  # (N, 2) each box's ground velocity, m/s (None: one frame, not known)
    box_classes: Tensor | None = None  # (N,) class index of each box
    actor_ids: list[int] = field(default_factory=list)  # (N,) the scenario's actor id of each box
    surface_depth: Tensor | None = None  # (V, H, W) planar depth, metres (model.surface_depth only)
    scenario: str = ""
    variant: str = ""  # lighting variant
    frame: int = 0  # the frame of a sequence (the ground truth's)
    fps: float | None = None  # the sequence's frames per second (None: one frame)
    view_frames: list[int] = field(default_factory=list)  # the frame each view's image and pose are of (delay)
    views: list[int] = field(default_factory=list)  # camera indices in the scenario
    camera_names: list[str] = field(default_factory=list)
    original_sizes: list[tuple[int, int]] = field(default_factory=list)  # each view's (width, height) as rendered
    mirrored: bool = False  # the whole item mirrored (data.hflip)
    shifts: list[tuple[int, int]] = field(default_factory=list)  # each view's (dx, dy) pixels (data.shift_px)
    # the positions whose sight a ground grid covers (None: ``scored``): a delayed item scores one view of a
    # camera group but keeps the group's grid, so it is scored on what the item without a delay is
    footprint: list[int] | None = None

    def pin_memory(self) -> "Item":
        """This item with its image tensors in pinned memory (a DataLoader's pinning thread calls it), so their copy
        to a GPU runs asynchronously."""
        pinned = {k: getattr(self, k).pin_memory() for k in ("images", "K", "camera_to_world")}
        return replace(self, **pinned)

    @property
    def grid_views(self) -> list[int]:
        """The views a ground grid over the item's sight covers."""
        return list(self.scored if self.footprint is None else self.footprint)
