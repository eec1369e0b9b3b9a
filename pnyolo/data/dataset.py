"""A torch Dataset over a dataset_spec folder: one item = one scenario at one frame under one lighting
variant (``ItemKey``; a scenario of one frame has frame 0 only).

Each item holds V source views (random in training, given in evaluation) resized by
``image_scale`` with K scaled to match, the same colour jitter for all its views, and YOLO
ground truth per view (the model kind builds its own training targets from it: ``Model.targets``).
2D labels come from the projection tool's files (``labels.json`` per view).

Example::

    ds = MultiViewDataset("out/dataset", "train", cfg, training=True)
    item = ds[0]                # a pnyolo.data.item.Item
    item.images.shape           # (V, 3, H, W) float in [0, 1]
    model.targets(item)         # its training targets: the kind builds them from item.gt
    item.surface_depth          # (V, H, W) planar depth in metres, sky SKY_DEPTH_M, NaN unknown
                                # (only with model.surface_depth)
    item.scored                 # positions of the views evaluation scores (all, except in the last
                                # group of an ``every_camera`` dataset; see ``camera_groups``)
    item.boxes_3d               # (N, 7) [cx, cy, cz, length, width, height, yaw] of the scenario's road
                                # users (world metres, mirrored with the item); item.gt[v].object_rows
                                # and the targets' object channel index it; item.box_classes (N,)
    item.cameras                # per view (ViewCamera): near, far, mounted_on, original size, the label
                                # thresholds (what a 3D detection projected into the view is held to)
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset as TorchDataset

from dataset_spec import Dataset, SpecError
from dataset_spec.cli_support import UserError
from pnyolo.config import Config
from pnyolo.config.checks import check_work
from pnyolo.data.augment import clip_shifted_box, color_jitter, item_box, mirror_and_shift
from pnyolo.data.grid import GridSpec, grid_for
from pnyolo.data.item import Item, ViewCamera, ViewGroundTruth

class ItemKey(NamedTuple):
    """What one item shows: a scenario at a frame under a lighting variant, with its views: ``group``
    (camera indices, positions scored), None: chosen per draw (``choose_views``); ``target``: with a delay,
    the one position of the group this item scores (its view at the frame, the others late)."""
    scenario: str
    frame: int
    variant: str
    group: tuple[list[int], list[int]] | None
    target: int | None = None


SKY_DEPTH_M = 100.0  # the depth a surface-depth target gives pixels without a surface (sky)


def open_dataset(root: str | Path) -> Dataset:
    try:
        return Dataset.open(root)
    except SpecError as exc:
        raise UserError(str(exc)) from None


def check_labels(ds: Dataset, scenarios: list[str], class_names: list[str]) -> None:
    """One clear error when any view of the given scenarios has no labels.json, or labels a road
    user the scenario's actor table has no 3D box for (targets and 3D metrics need the box)."""
    missing = [f"{s}/{c.name}" + (f" frame {f}" if f else "") for s in scenarios for f in ds.frames(s)
               for c in ds.scenario(s).cameras if not ds.layout.labels(s, c.name, f).is_file()]
    if missing:
        raise UserError(f"{len(missing)} view(s) have no 2D labels (e.g. {missing[0]}); "
                        f"run the projection tool first: project-labels {ds.root}")
    for s in scenarios:
        scn = ds.scenario(s)
        boxed = {a.id for a in scn.actors if a.cls in class_names}
        for f, c in ((f, c) for f in ds.frames(s) for c in scn.cameras):
            stray = [lab.instance_id for lab in ds.read_labels(s, c.name, f).objects
                     if lab.cls in class_names and lab.instance_id not in boxed]
            if stray:
                raise UserError(f"{s}/{c.name}: labels name road user {stray[0]}, which has no 3D box in the "
                                f"scenario's actor table (re-run project-labels, or re-export the dataset with its actors)")


def camera_groups(num_cameras: int, group_size: int) -> list[tuple[list[int], list[int]]]:
    """Items that score every camera of a scenario once, each with ``group_size`` - 1 other cameras
    as source views: (camera indices, positions scored). Consecutive cameras form the groups; the
    last group, if short, is completed with cameras from the start, which there only serve as
    source views. 5 cameras in groups of 3: ([0, 1, 2], [0, 1, 2]) and ([3, 4, 0], [0, 1])."""
    if not 1 <= group_size <= num_cameras:
        raise ValueError(f"groups of {group_size} from {num_cameras} cameras")
    return [([(start + j) % num_cameras for j in range(group_size)],
             [j for j in range(group_size) if start + j < num_cameras])
            for start in range(0, num_cameras, group_size)]


def delay_frames(ds: Dataset, scenario: str, delay_ms: float, option: str = "--delay-ms") -> int:
    """``delay_ms`` as whole frames of ``scenario`` (one-line errors naming ``option``, the command's option that
    gave it: not a multiple of its frame interval, naming the nearest delays that are, or longer than the sequence)."""
    scn = ds.scenario(scenario)
    if delay_ms < 0:
        raise UserError(f"{option} must be >= 0, got {delay_ms:g}")
    if scn.frames == 1:
        raise UserError(f"{option} {delay_ms:g}: scenario {scenario} is one frame, not a sequence")
    step = 1000.0 / scn.fps
    k = delay_ms / step
    if abs(k - round(k)) > 1e-6:
        lo, hi = math.floor(k) * step, math.ceil(k) * step
        raise UserError(f"{option} {delay_ms:g}: scenario {scenario} has a frame every {step:g} ms; the nearest "
                        f"values are {lo:g} and {hi:g} ms")
    if round(k) >= scn.frames:
        raise UserError(f"{option} {delay_ms:g}: scenario {scenario} lasts {scn.frames} frames of {step:g} ms: "
                        "no frame that much earlier than any other")
    return int(round(k))


def road_user_boxes(scenario, class_names: list[str], mirrored: bool) -> tuple[torch.Tensor, list[int], torch.Tensor]:
    """(N, 7) [cx, cy, cz, length, width, height, yaw] of the scenario's actors of the detector's
    classes, sorted by id, their ids and their class indices (N,); ``mirrored``: in the world
    mirrored in x = 0 that mirrored items show (``dataset_spec.camera.mirror_camera``): cx -> -cx,
    yaw -> pi - yaw."""
    actors = sorted((a for a in scenario.actors if a.cls in class_names), key=lambda a: a.id)
    rows = []
    for a in actors:
        (cx, cy, cz), (length, width, height) = a.box.center, a.box.size
        rows.append([-cx, cy, cz, length, width, height, math.pi - a.box.yaw] if mirrored
                    else [cx, cy, cz, length, width, height, a.box.yaw])
    classes = torch.tensor([class_names.index(a.cls) for a in actors], dtype=torch.long)
    return torch.tensor(rows, dtype=torch.float32).reshape(-1, 7), [a.id for a in actors], classes


class Delay(NamedTuple):
    """The other cars' views late (evaluation of sequences): ``ms`` behind the scored view's frame, the items
    starting ``from_ms`` into each sequence at the earliest (a sweep over delays scores the same frames at every
    delay, 0 included)."""
    ms: float = 0.0
    from_ms: float = 0.0


class Draw(NamedTuple):
    """An item's random choices, given or drawn: ``mirror`` None, mirrored at random when training with
    ``data.hflip``; ``shifts`` (one (dx, dy) per view) None, random within ``data.shift_px`` when training;
    ``generator``, what they are drawn from (None: torch's global generator)."""
    mirror: bool | None = None
    shifts: list[tuple[int, int]] | None = None
    generator: torch.Generator | None = None


class MultiViewDataset(TorchDataset):
    def __init__(self, root: str | Path, split: str, cfg: Config, training: bool = False,
                 views: list[int] | None = None, scenarios: list[str] | None = None, every_camera: bool = False,
                 delay: Delay = Delay()):
        """``views``: the camera indices of every item (None: random ``data.num_views`` in training,
        the first ones otherwise). ``every_camera`` (evaluation): every camera of each scenario is
        scored once, in items of ``data.num_views`` cameras (``camera_groups``). ``delay`` (evaluation
        of sequences): the items without a delay, each scored view in an item of its own: that view at the
        frame, the group's other views (the other cars' messages) of the frame ``delay.ms`` earlier, the group's
        ground grid (``Item.footprint``), so a delay scores exactly what no delay scores (frames without an
        earlier one are left out)."""
        delay_ms, from_ms = delay
        if every_camera and (training or views is not None):
            raise UserError("every_camera is for evaluation and chooses the views itself (no views list)")
        if (delay_ms or from_ms) and training:
            raise UserError("delay_ms is for evaluation")
        self.ds = open_dataset(root)
        self.cfg, self.training = cfg, training
        self.class_names = self.ds.info.detectable_classes
        if scenarios is None:
            try:
                scenarios = self.ds.split(split)
            except SpecError as exc:
                raise UserError(str(exc)) from None
        if not scenarios:
            raise UserError(f"split {split!r} of {self.ds.root} has no scenarios")
        self.scenarios = scenarios
        if cfg.model.reads_depth_maps() and not self.ds.info.has("depth"):
            raise UserError(f"{self.ds.root} has no depth maps (camera data: dataset.json 'absent'); "
                            "model.surface_depth needs them: set it to false and model.loss.surface_depth to 0")
        check_labels(self.ds, scenarios, self.class_names)
        self.delay_frames = {s: delay_frames(self.ds, s, delay_ms) for s in scenarios} if delay_ms or from_ms else {}
        first = {s: max(self.delay_frames[s], delay_frames(self.ds, s, from_ms, "--from-ms"))
                 for s in self.delay_frames}
        self.frames_left_out = sum(first.values())  # frames too early in their sequence for the delay (or from_ms)
        self.items: list[ItemKey] = []
        for s in scenarios:
            scn = self.ds.scenario(s)
            check_work(cfg, self.grid(s))  # image, cells and 3D points within budget before any item is built
            if len(scn.cameras) < cfg.data.num_views and views is None:
                raise UserError(f"scenario {s} has {len(scn.cameras)} cameras; data.num_views is {cfg.data.num_views}")
            if views is not None:
                bad = [v for v in views if not 0 <= v < len(scn.cameras)]
                if bad:
                    raise UserError(f"view index {bad[0]} out of range: scenario {s} has {len(scn.cameras)} "
                                    f"cameras (0..{len(scn.cameras) - 1})")
            n, size = len(scn.cameras), len(views) if views is not None else cfg.data.num_views
            groups = camera_groups(n, size) if every_camera else [None]
            delayed = bool(self.delay_frames.get(s))
            if delayed and not every_camera:
                groups = [(self.choose_first(views, size), list(range(size)))]
            for frame in self.ds.frames(s)[first.get(s, 0):]:
                for var in scn.lighting:
                    if cfg.data.variants is None or var.name in cfg.data.variants:
                        self.items += [ItemKey(s, frame, var.name, group, target) for group in groups
                                       for target in (group[1] if delayed else [None])]
        if not self.items:
            raise UserError(f"no (scenario, frame, lighting variant) items in split {split!r} (data.variants={cfg.data.variants})")
        self.views = views
        # Decoded, resized images (uint8) and labels, kept while they fit data.cache_mb: small
        # datasets (overfitting, CPU runs) then read and resize every file once.
        self._cache: dict = {}
        self._cache_bytes = 0

    def __len__(self) -> int:
        return len(self.items)

    def grid(self, scenario: str) -> GridSpec:
        cam = self.ds.scenario(scenario).cameras[0]
        return grid_for(cam.width, cam.height, self.cfg.data.image_scale, self.cfg.data.cell_px)

    def choose_views(self, scenario: str, generator: torch.Generator | None = None) -> list[int]:
        n = len(self.ds.scenario(scenario).cameras)
        if self.views is not None:
            return list(self.views)
        if self.training:
            return torch.randperm(n, generator=generator)[: self.cfg.data.num_views].tolist()
        return list(range(self.cfg.data.num_views))

    def _cached(self, key, make, nbytes: int):
        if key in self._cache:
            return self._cache[key]
        value = make()
        if self._cache_bytes + nbytes <= self.cfg.data.cache_mb * 2**20:
            self._cache[key] = value
            self._cache_bytes += nbytes
        return value

    def __getitem__(self, index: int) -> Item:
        return self.draw(index)

    def draw(self, index: int, generator: torch.Generator | None = None) -> Item:
        """Item ``index`` with its random choices (training: views, mirror, shifts, colour) drawn from
        ``generator`` (None: torch's global generator, as ``dataset[index]``)."""
        key = self.items[index]
        if key.group is None:
            return self.load(key.scenario, key.variant, self.choose_views(key.scenario, generator), frame=key.frame,
                             draw=Draw(generator=generator))
        if key.target is None:
            return self.load(key.scenario, key.variant, *key.group, frame=key.frame)
        earlier = key.frame - self.delay_frames[key.scenario]
        return self.load(key.scenario, key.variant, key.group[0], [key.target], frame=key.frame,
                         late=(earlier, key.group[1]))

    @staticmethod
    def choose_first(views: list[int] | None, size: int) -> list[int]:
        """The views of a delayed item without ``every_camera``: the given ones, or the first ``size``."""
        return list(views) if views is not None else list(range(size))

    def load(self, scenario: str, variant: str, view_indices: list[int], scored: list[int] | None = None,
             frame: int = 0, late: tuple[int, list[int]] | None = None, draw: Draw = Draw()) -> Item:
        """One item at ``frame``; ``scored``: the view positions evaluation scores (None: all); ``late``:
        (source frame, footprint), the frame the views not scored show (their images and poses: a delayed message;
        the ground truth is of ``frame``, and a road user counts as seen in another view by what that view's image
        shows) and the positions a ground grid covers (None: the scored ones); ``draw``: the random choices. Its
        training targets are the model's to build from its ground truth (``Model.targets``)."""
        source_frame, footprint = late or (None, None)
        mirror, shifts, generator = draw
        scn = self.ds.scenario_at(scenario, frame)
        g = self.grid(scenario)
        cams = [scn.cameras[i] for i in view_indices]
        shown = [frame if source_frame is None or scored is None or k in scored else source_frame
                 for k in range(len(cams))]  # the frame each view's image and pose are of
        posed = [self.ds.scenario_at(scenario, f).cameras[i] for f, i in zip(shown, view_indices)]
        images, Ks, c2ws, gts, depths = [], [], [], [], []
        # Mirror augmentation: the same mirrored world seen by mirrored cameras, so the views stay
        # geometrically consistent (flipping images alone would break the multi-view geometry).
        flip = (self.training and self.cfg.data.hflip and bool(torch.rand((), generator=generator) < 0.5)) \
            if mirror is None else mirror
        if shifts is None:  # no random draw without a shift: runs without it stay reproducible
            r = self.cfg.data.shift_px if self.training else 0
            shifts = [tuple(torch.randint(-r, r + 1, (2,), generator=generator).tolist()) if r else (0, 0) for _ in cams]
        if len(shifts) != len(cams):
            raise ValueError(f"{len(shifts)} shifts for {len(cams)} views")
        def labels_at(c, at):
            return self._cached(("labels", scenario, at, c.name), lambda: self.ds.read_labels(scenario, c.name, at), 4096)
        labels = {c.name: labels_at(c, frame) for c in cams}
        seen_in = {c.name: labels_at(c, at) for c, at in zip(cams, shown)}  # what each view's image shows
        boxes_3d, actor_ids, box_classes = road_user_boxes(scn, self.class_names, flip)
        row_of = {aid: k for k, aid in enumerate(actor_ids)}  # check_labels: every label has a row
        for cam, pose, at, shift in zip(cams, posed, shown, shifts):
            def read(cam=cam, at=at):
                rgb = self.ds.read_rgb(scenario, cam.name, variant, at)
                if rgb.shape[:2] != (g.height, g.width):
                    rgb = cv2.resize(rgb, (g.width, g.height), interpolation=cv2.INTER_AREA)
                return rgb
            rgb = mirror_and_shift(self._cached(("rgb", scenario, at, cam.name, variant), read,
                                                g.width * g.height * 3), flip, shift)
            images.append(torch.from_numpy(rgb).permute(2, 0, 1).float() / 255.0)
            if self.cfg.model.reads_depth_maps():
                depths.append(torch.from_numpy(self._surface_depth(scenario, cam, g, flip, shift, at)))
            view = pose.resized(g.width, g.height)  # the camera of the image as the item shows it
            view = (view.mirrored() if flip else view).shifted(*shift)
            Ks.append(torch.tensor(view.K, dtype=torch.float32))
            c2ws.append(torch.tensor(view.camera_to_world, dtype=torch.float32))
            gts.append(self._ground_truth(cam, cams, {**seen_in, cam.name: labels[cam.name]}, g, flip, shift, row_of))
        imgs = torch.stack(images)
        if self.training and self.cfg.data.color_jitter:
            imgs = color_jitter(imgs, self.cfg.data.jitter_hue, self.cfg.data.jitter_strength, generator)
        return Item(imgs, torch.stack(Ks), torch.stack(c2ws), g,
                    [ViewCamera(c.near, c.far, (c.width, c.height), labels[c.name].thresholds, c.mounted_on) for c in cams],
                    self.class_names, list(range(len(cams)) if scored is None else scored), gt=gts,
                    boxes_3d=boxes_3d, box_classes=box_classes, actor_ids=actor_ids,
                    velocities=self._velocities(scenario, frame, actor_ids, flip),
                    surface_depth=torch.stack(depths) if depths else None, scenario=scenario, variant=variant, frame=frame,
                    fps=scn.fps, view_frames=shown,
                    views=list(view_indices), camera_names=[c.name for c in cams],
                    original_sizes=[(c.width, c.height) for c in cams], mirrored=flip,
                    shifts=[tuple(s) for s in shifts], footprint=footprint)

    def _velocities(self, scenario: str, frame: int, actor_ids: list[int], mirrored: bool) -> torch.Tensor | None:
        """(N, 2) the road users' ground velocities at ``frame`` (frames.json; mirrored in x with the item), None for
        a scenario of one frame (no motion is known)."""
        if self.ds.scenario(scenario).frames < 2:
            return None
        actors = self.ds.sequence(scenario).frames[frame].actors
        v = np.array([actors[a].velocity[:2] if a in actors else (0.0, 0.0) for a in actor_ids], dtype=np.float64)
        return torch.from_numpy(v.reshape(-1, 2) * ([-1.0, 1.0] if mirrored else [1.0, 1.0])).float()

    def _ground_truth(self, cam, cams, labels: dict, g: GridSpec, flip: bool, shift, row_of: dict) -> ViewGroundTruth:
        """One view's ground truth in the pixels of the item's image (mirrored and shifted like it): the
        road users its label thresholds keep, and those they (or the shift) leave out."""
        sx, sy = g.width / cam.width, g.height / cam.height
        classes, boxes, vis, seen, dist, rows, other_px = [], [], [], [], [], [], []
        excluded, excluded_rows, excluded_classes = [], [], []  # road users the label thresholds leave out
        view_labels = labels[cam.name]
        for lab in view_labels.objects:
            if lab.cls not in self.class_names:
                continue
            box = item_box(lab.box, cam.width, sx, sy, flip, shift)
            clipped = clip_shifted_box(box, g.width, g.height) if shift != (0, 0) else box
            box = box if clipped is None else clipped
            if clipped is None or not view_labels.thresholds.accepts(lab):  # moved out of the frame, or left out
                excluded.append(box)
                excluded_rows.append(row_of[lab.instance_id])
                excluded_classes.append(self.class_names.index(lab.cls))
                continue
            classes.append(self.class_names.index(lab.cls))
            boxes.append(box)
            vis.append(np.nan if lab.visible_fraction is None else lab.visible_fraction)  # nan: not measured
            dist.append(lab.distance)
            rows.append(row_of[lab.instance_id])
            # another view's label of unknown visibility (camera data) counts as seen there
            elsewhere = [o.visible_pixels for other in cams if other.name != cam.name
                         for o in labels[other.name].objects if o.instance_id == lab.instance_id]
            seen.append(any(p is None or p > 0 for p in elsewhere))
            other_px.append(max((p for p in elsewhere if p is not None), default=0))
        return ViewGroundTruth(
            np.array(boxes).reshape(-1, 4), np.array(classes, dtype=np.int64), np.array(vis, dtype=np.float64),
            np.array(seen, dtype=bool), np.array(dist, dtype=np.float64),
            excluded_boxes=np.array(excluded).reshape(-1, 4), other_view_pixels=np.array(other_px, dtype=np.int64),
            excluded_classes=np.array(excluded_classes, dtype=np.int64), object_rows=np.array(rows, dtype=np.int64),
            excluded_rows=np.array(excluded_rows, dtype=np.int64))

    def instance_maps(self, item: Item) -> np.ndarray:
        """(V, H, W) int32: each view's instance ids as the item sees it (its size, mirrored and
        shifted like its image; nearest pixel, the shift's border 0)."""
        g = item.grid
        out = []
        for name, shift in zip(item.camera_names, item.shifts):
            ids = self.ds.read_instance(item.scenario, name, item.frame).astype(np.int32)
            if ids.shape != (g.height, g.width):
                ids = cv2.resize(ids, (g.width, g.height), interpolation=cv2.INTER_NEAREST)
            out.append(mirror_and_shift(ids, item.mirrored, tuple(shift)))
        return np.stack(out)

    def _surface_depth(self, scenario: str, cam, g: GridSpec, flip: bool, shift: tuple[int, int],
                       frame: int = 0) -> np.ndarray:
        """A view's planar depth at the item's size (nearest pixel: no depths blended across an
        edge), mirrored and shifted like its image; sky SKY_DEPTH_M, the shift's border NaN."""
        def read():
            d = self.ds.read_depth(scenario, cam.name, frame)
            if d.shape != (g.height, g.width):
                d = cv2.resize(d, (g.width, g.height), interpolation=cv2.INTER_NEAREST)
            return np.where(d > 0, d, SKY_DEPTH_M).astype(np.float32)
        return mirror_and_shift(self._cached(("depth", scenario, frame, cam.name), read, g.width * g.height * 4), flip,
                                shift, fill=np.nan)

