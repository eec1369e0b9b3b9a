"""One example as every model, loss, metric and picture reads it: the source views of one scene under
one lighting variant. Built by the dataset (``pnyolo.data.dataset``, with ground truth) and by the
inference API (``pnyolo.inference``, without)::

    item = dataset[0]
    item.images.shape           # (V, 3, H, W) float in [0, 1]
    item.K, item.camera_to_world  # (V, 3, 3) at the encoded size, (V, 4, 4) world metres
    item.targets.shape          # (V, S_h, S_w, A, TARGET_CHANNELS)
    item.gt[v]["boxes"]         # view v's ground truth (pixels of the encoded image)
    dataclasses.replace(item, camera_to_world=moved)   # the same item with other poses
"""
from __future__ import annotations

from dataclasses import dataclass, field

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
class Item:
    images: Tensor  # (V, 3, H, W) in [0, 1]
    K: Tensor  # (V, 3, 3) intrinsics of the encoded images
    camera_to_world: Tensor  # (V, 4, 4)
    grid: GridSpec  # the encoded size and YOLO grid
    cameras: list[ViewCamera]
    class_names: list[str]
    scored: list[int]  # positions of the views evaluation scores (the others are source views only)
    targets: Tensor | None = None  # (V, S_h, S_w, A, TARGET_CHANNELS) YOLO targets
    unseen_elsewhere_cells: Tensor | None = None  # (V, S_h, S_w) bool: cells of road users no other view sees
    gt: list[dict] = field(default_factory=list)  # per view: boxes, classes, visibility, rows into boxes_3d, ...
    boxes_3d: Tensor | None = None  # (N, 7) [cx, cy, cz, length, width, height, yaw] world metres
    box_classes: Tensor | None = None  # (N,) class index of each box
    actor_ids: list[int] = field(default_factory=list)  # (N,) the scenario's actor id of each box
    surface_depth: Tensor | None = None  # (V, H, W) planar depth, metres (model.surface_depth only)
    scenario: str = ""
    variant: str = ""  # lighting variant
    views: list[int] = field(default_factory=list)  # camera indices in the scenario
    camera_names: list[str] = field(default_factory=list)
    original_sizes: list[tuple[int, int]] = field(default_factory=list)  # each view's (width, height) as rendered
    mirrored: bool = False  # the whole item mirrored (data.hflip)
    shifts: list[tuple[int, int]] = field(default_factory=list)  # each view's (dx, dy) pixels (data.shift_px)
