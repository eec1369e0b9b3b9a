"""What a config may hold: every numeric knob's range, every option's choices, and the relations
between values, checked once where a config is loaded (``pnyolo.config.load_config``), each a
one-line ``UserError``.

    if value not in RANGES["train.lr"]: ...        # Interval: "> 0"
    validate(cfg)                                 # raises UserError naming the key
"""
from __future__ import annotations

import math

from dataclasses import dataclass

from dataset_spec.cli_support import UserError
from dataset_spec.names import excerpt

EVAL_STATS = ("running", "item")  # model.encoder.eval_stats: batch-norm statistics outside training
MAX_CONFIG_VALUES = 100_000  # a config, every alias and shared reference expanded, holds at most this many values


def check_expansion(obj, where: str, limit: int = MAX_CONFIG_VALUES) -> None:
    """One-line ``UserError`` when ``obj`` (a loaded YAML file, a ``--set`` value, a checkpoint's config) holds
    more than ``limit`` values with its YAML aliases or shared references expanded: an alias bomb of a few hundred
    bytes is refused while loading, before a copy, a message or a report expands it (the walk stops at the limit)."""
    stack, count = [obj], 0
    while stack:
        node = stack.pop()
        count += 1
        if count > limit:
            raise UserError(f"{where}: expands to more than {limit} values (YAML aliases or shared references "
                            "nested into each other); write the values out")
        if isinstance(node, dict):
            stack.extend(node.values())
        elif isinstance(node, (list, tuple)):
            stack.extend(node)


@dataclass(frozen=True)
class Interval:
    """Allowed values of a number, always finite (NaN and infinity are no setting: ``train.lr=.inf`` would pass
    ``> 0`` and fail in the first step); ``open_low`` / ``open_high`` exclude that end."""

    low: float | None = None
    high: float | None = None
    open_low: bool = False
    open_high: bool = False

    def __contains__(self, value) -> bool:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        if isinstance(value, float) and not math.isfinite(value):  # an int is finite (and may exceed a float)
            return False
        if self.low is not None and (value < self.low or (self.open_low and value == self.low)):
            return False
        return not (self.high is not None and (value > self.high or (self.open_high and value == self.high)))

    def __str__(self) -> str:
        def num(v: float) -> str:  # whole numbers written out (1048576, not 1.04858e+06)
            return str(int(v)) if float(v).is_integer() and abs(v) < 1e15 else f"{v:g}"

        if self.high is None:
            return f"{'>' if self.open_low else '>='} {num(self.low)}"
        return f"in {'(' if self.open_low else '['}{num(self.low)}, {num(self.high)}{')' if self.open_high else ']'}"


AT_LEAST_0, AT_LEAST_1, POSITIVE = Interval(0), Interval(1), Interval(0, open_low=True)
SHARE, SHARE_OPEN_HIGH = Interval(0, 1), Interval(0, 1, open_high=True)
METRES = Interval(-1000, 1000)  # a world height or offset
# What one item may ask of a machine, whatever a config (a checkpoint's from someone else too) says: the sizes
# derived from several keys, checked where they are derived (pnyolo.data.grid, a kind's check_work), before
# anything of that size is allocated.
MAX_IMAGE_SIDE = 8192  # encoded image pixels per side (the readers' cap on a stored image)
MAX_GRID_CELLS = 1 << 20  # YOLO grid cells per view
# The 3D points a kind queries per view (rays x samples per ray) are held whole in float32 tensors: a point's
# position, direction and depth (7 numbers) and its place in every view (2 each), several times over as the
# sampler builds them (about 4 copies). Their bytes are bounded by what fits beside a model in a machine's memory.
MAX_SAMPLE_BYTES = 1 << 30


def sample_bytes(points: int, views: int) -> int:
    """Bytes of the per-point tensors ``points`` 3D points of ``views`` views take (the budget's measure)."""
    return points * 4 * 4 * (7 + 2 * views)
# Every shared numeric knob's range, checked where a config is loaded (a kind's own: its config class's). Keys no
# tensor shape depends on (the checkpoint loader compares shapes) are bounded above where they size work.
RANGES: dict[str, Interval] = {
    "data.num_views": Interval(1, 64), "data.image_scale": Interval(0, 8, open_low=True),
    "data.cell_px": Interval(1, 1024), "data.shift_px": Interval(0, 1024), "data.ground_z": METRES,
    "data.jitter_hue": Interval(0, 0.5), "data.jitter_strength": SHARE_OPEN_HIGH, "data.cache_mb": Interval(0, 1 << 20),
    "model.encoder.num_layers": Interval(1, 5), "model.encoder.context_channels": AT_LEAST_0,
    "model.encoder.fpn_channels": AT_LEAST_1, "train.encoder_lr_scale": POSITIVE,
    "model.encoder.context_dilation": AT_LEAST_1, "model.head.ignore_threshold": SHARE, "eval.centre_nms_m": AT_LEAST_0,
    **{f"model.loss.{k}": AT_LEAST_0 for k in ("box", "obj", "noobj", "cls", "hidden_weight", "unseen_weight", "depth",
                                               "iou", "surface_depth", "occupancy", "heatmap", "regression",
                                               "state")},
    "train.epochs": AT_LEAST_1, "train.lr": POSITIVE, "train.lr_decay": Interval(0, 1, open_low=True),
    "train.lr_min_ratio": SHARE, "train.lr_schedule_steps": AT_LEAST_0, "train.threads": Interval(0, 1024),
    "train.max_steps": AT_LEAST_0, "train.checkpoint_every": AT_LEAST_0, "train.items_per_step": Interval(1, 4096),
    "train.seed": Interval(0, 2**32 - 1),
    "train.workers": Interval(0, 64),
    "train.save_every_epochs": AT_LEAST_1, "train.keep_checkpoints": AT_LEAST_0,
    "train.val_every": AT_LEAST_0, "train.vis_every": AT_LEAST_0, "train.log_every": AT_LEAST_1,
    "train.max_bad_steps": AT_LEAST_1, "train.grad_clip": AT_LEAST_0, "train.ema_decay": SHARE_OPEN_HIGH,
    "train.background_rays": Interval(0, 1, open_low=True), "train.own_view_dropout": SHARE_OPEN_HIGH,
    "eval.conf_threshold": SHARE, "eval.nms_iou": Interval(0, 1, open_low=True),
    "eval.select_iou": Interval(0, 1, True, True), "eval.depth_peaks": Interval(1, 8), "eval.peak_gap": POSITIVE,
    "model.head.obj_bias_init": Interval(-100, 100),
}
CHOICES: dict[str, tuple[str, ...]] = {
    "model.encoder.backbone": ("resnet18", "resnet34", "efficientnet_lite0"), "model.encoder.norm": ("batch", "frozen_batch"),
    "model.encoder.eval_stats": EVAL_STATS, "model.loss.obj_target": ("iou", "one"),
    "model.loss.obj_loss": ("mse", "bce"),
    "train.lr_schedule": ("exponential", "cosine"), "train.amp": ("none", "bf16"),
}


_ABSENT = object()


def _get(cfg, key: str):
    """The value at ``key``, or ``_ABSENT`` where the config's model kind has no such section."""
    node = cfg
    for part in key.split("."):
        node = getattr(node, part, _ABSENT)
        if node is _ABSENT:
            return node
    return node


def validate(cfg) -> None:
    """Every value and relation of a config, checked once where it is loaded (one-line UserError)."""
    own_ranges = {f"model.{k}": v for k, v in cfg.model.ranges.items()}
    for key, allowed in {**RANGES, **own_ranges}.items():
        if _get(cfg, key) is not _ABSENT and _get(cfg, key) not in allowed:
            raise UserError(f"config {key} must be {allowed}, got {excerpt(_get(cfg, key))}")
    for key, options in {**CHOICES, **{f"model.{k}": v for k, v in cfg.model.choices.items()}}.items():
        if _get(cfg, key) is not _ABSENT and _get(cfg, key) not in options:
            raise UserError(f"config {key}: {excerpt(_get(cfg, key))} ({' | '.join(options)})")
    cfg.model.check(cfg)
    if cfg.eval.depth_gap is not None and not cfg.eval.depth_gap > 0:
        raise UserError(f"config eval.depth_gap: metres > 0 or null (plain NMS), got {excerpt(cfg.eval.depth_gap)}")
    for key in ("late_send", "late_keep"):
        if getattr(cfg.eval, key) is not None and getattr(cfg.eval, key) not in SHARE:
            raise UserError(f"config eval.{key}: a score in [0, 1] or null, got {excerpt(getattr(cfg.eval, key))}")
    cal = cfg.eval.late_calibration
    if cal is not None and (not isinstance(cal, list) or len(cal) != 3 or not all(v in Interval() for v in cal)):
        raise UserError(f"config eval.late_calibration: [a, b, c], three finite numbers, or null, got {excerpt(cal)}")
    ious = cfg.eval.match_ious
    if not ious or not all(t in RANGES["eval.select_iou"] for t in ious):
        raise UserError(f"config eval.match_ious: a non-empty list of IoUs in (0, 1), got {excerpt(ious)}")
    if f"{cfg.eval.select_iou:.1f}" not in {f"{t:.1f}" for t in ious}:
        raise UserError(f"config eval.select_iou {cfg.eval.select_iou} must be one of eval.match_ious {excerpt(ious)}")
    if cfg.eval.views is not None and (not cfg.eval.views or any(not isinstance(v, int) or v < 0
                                                                  for v in cfg.eval.views)):
        raise UserError(f"config eval.views: camera indices >= 0 or null, got {excerpt(cfg.eval.views)}")
    if cfg.data.variants is not None and (not cfg.data.variants or not all(isinstance(v, str) for v in cfg.data.variants)):
        raise UserError(f"config data.variants: lighting variant names or null (all), got {excerpt(cfg.data.variants)}")
    if not cfg.model.casts_rays:  # the other sections' settings that only rays honour
        rays_only = {"eval.depth_peaks": cfg.eval.depth_peaks > 1,
                     "train.own_view_dropout": cfg.train.own_view_dropout > 0,
                     "train.background_rays": cfg.train.background_rays < 1}
        key = next((k for k, on in rays_only.items() if on), None)
        if key:
            raise UserError(f"config {key}: the {cfg.model.kind} model casts no rays (leave it at its default)")
    pn = cfg.train.pose_noise
    if pn is not None and (len(pn) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                   and 0 <= v < float("inf") for v in pn)):
        raise UserError(f"config train.pose_noise: [sigma metres, sigma degrees] >= 0 or null, got {excerpt(pn)}")


def check_work(cfg, grid) -> None:
    """One line when an item of ``grid`` (a ``GridSpec``) would make ``cfg``'s kind query 3D points whose tensors
    take more than ``MAX_SAMPLE_BYTES`` a view (``sample_bytes``): checked before an item is built, whatever the
    config's source."""
    points = grid.grid_w * grid.grid_h * cfg.model.points_per_cell()
    need = sample_bytes(points, cfg.data.num_views)
    if need > MAX_SAMPLE_BYTES:
        raise UserError(f"config: {grid.grid_w}x{grid.grid_h} cells x {cfg.model.points_per_cell()} points a cell "
                        f"(model.sampler) = {points} 3D points a view, above the memory budget ({need / 2 ** 30:.1f} "
                        f"GiB of sample tensors for {cfg.data.num_views} views; at most {MAX_SAMPLE_BYTES / 2 ** 30:g})")
