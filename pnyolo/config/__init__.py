"""Configuration as nested dataclasses: one name per knob.

A config file (YAML) holds any subset of the fields; ``--set section.key=value`` overrides
one value (parsed as YAML, so ``--set train.epochs=3`` gives an int). Unknown keys are user
errors, never silently ignored.

Example::

    cfg = load_config("configs/cpu.yaml", ["model.kind=pixelnerf-yolo", "train.epochs=2"])
    cfg.model.sampler.num_samples  # 16
    to_dict(cfg)                   # plain dict, stored in every checkpoint

The ``model`` section is the chosen kind's class (its model's ``config_class``, found through
``pnyolo.registry``): ``--set`` a key that
kind does not have and it is refused; a config file may hold sections for several kinds (a base
every kind shares), each kind reading its own.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from dataset_spec.cli_support import UserError
from dataset_spec.names import excerpt
from pnyolo.config.checks import check_expansion, validate
from pnyolo.config.model import (DEFAULT_KIND, EncoderConfig, GridModelConfig, HeadConfig,  # noqa: F401
                                 ImageModelConfig, ModelConfig, field_names, has_path, keys_for_kind)
from pnyolo.config.upgrades import (checkpoint_defaults, model_config_class as _model_class,  # noqa: F401
                                    moved_loss_overrides, upgrade_legacy)
from pnyolo.registry import config_class, kinds


@dataclass
class DataConfig:
    num_views: int = 3  # source views per item (random in training, given in evaluation)
    image_scale: float = 0.5  # encoded image size = round(scale * original size)
    cell_px: float = 30.0  # YOLO grid cell size in encoded-image pixels (grid = round(size / cell_px))
    color_jitter: bool = True  # the same jitter for all views of an item (training only)
    hflip: bool = False  # training only: with probability 1/2 mirror the whole item (every image flipped
    #                      left-right, every camera mirrored, see dataset_spec.camera.mirror_camera)
    # Training only: move each view's image by its own random whole-pixel offset in
    # [-shift_px, shift_px] on each axis (uncovered pixels black, the principal point moved with
    # it, see dataset_spec.camera.translate_intrinsics, so the geometry stays exact). A fixed
    # camera sees each object at one place in every lighting variant; the shift makes where an
    # object lies within its grid cell something to see rather than to remember per scene.
    shift_px: int = 0
    jitter_hue: float = 0.1  # hue shift of the colour jitter, a share of the hue circle
    jitter_strength: float = 0.1  # brightness/contrast/saturation factors in [1-s, 1+s]
    variants: list[str] | None = None  # lighting variants to use (None: all)
    cache_mb: float = 512.0  # keep decoded, resized images in memory up to this size (0: read every time)
    ground_z: float = 0.0  # world height of the road surface, metres (where rays are clipped, pillars stand)


@dataclass
class TrainConfig:
    epochs: int = 100  # passes over the training items
    lr: float = 1e-4  # Adam's learning rate
    lr_decay: float = 0.9  # exponential, per epoch (lr_schedule: exponential)
    lr_schedule: str = "exponential"  # exponential (per epoch) | cosine (per step, to lr_min_ratio * lr at the last step)
    lr_min_ratio: float = 0.02  # lr_schedule cosine: the last step's learning rate as a share of lr
    lr_schedule_steps: int = 0  # cosine length in steps (0: the run's length, min(epochs x items, max_steps))
    seed: int = 0  # seeds weights, item order, augmentation and ray sampling
    device: str = "auto"  # auto | cpu | cuda | cuda:N | mps
    # [sigma metres, sigma degrees]: every car's pose but the step's ego wrong by that much (the cooperative
    # setting's pose error, pnyolo.cooperation.pose_noise); null: exact poses
    pose_noise: list[float] | None = None
    encoder_lr_scale: float = 1.0  # the encoder backbone's learning rate as a share of lr (pretrained weights: < 1)
    threads: int = 0  # torch CPU threads in training and evaluation (0: the usable cores; pnyolo.engine.runtime)
    max_steps: int = 0  # stop after this many optimizer steps (0: no limit; for tests and smoke runs)
    # Items (scenes) whose gradients one optimizer step averages, per process: a step takes
    # processes x items_per_step items (the global batch; pnyolo-train --nproc N runs N processes).
    # The learning rate keeps its meaning: the loss is the mean over the global batch.
    items_per_step: int = 1
    # DataLoader worker processes that read, decode and augment the next items while the model trains on this
    # step's (0: in the training process, as always). Their augmentation draws come from a generator seeded by
    # (train.seed, rank, epoch, position): the same items, views and augmentation for any number of workers.
    workers: int = 0
    # bf16 autocast for forward and loss (bf16: the GPU's tensor cores; none: float32 throughout, as always)
    amp: str = "none"
    compile: bool = False  # torch.compile the model's image encoder (the part that dominates a step)
    # Deterministic algorithms (torch.use_deterministic_algorithms, cuBLAS's workspace setting, the samplers'
    # gather arithmetic instead of grid_sample and bilinear upsampling): a CUDA --resume then continues exactly;
    # without it CUDA's atomic additions in a few backward passes make the resumed run differ in the last bits.
    deterministic: bool = False
    checkpoint_every: int = 0  # also save 'latest' every N steps (0: per epoch only)
    save_every_epochs: int = 1  # epochs between the per-epoch outputs (latest, backup, vis); the last epoch always
    keep_checkpoints: int = 3  # epoch_XXXX.pt backups kept, the newest (0: every one; each is a whole checkpoint)
    val_every: int = 1  # epochs between validations (0: never)
    vis_every: int = 0  # steps between visualisation PNGs (0: once per epoch)
    log_every: int = 1  # steps between log.jsonl records
    max_bad_steps: int = 5  # stop after this many consecutive non-finite steps
    grad_clip: float = 10.0  # 0: off
    # Exponential moving average of the weights (pnyolo.engine.weight_average), 0: off. When on, validation,
    # best.pt and every checkpoint's ``model`` hold the average (what evaluation loads); the trained
    # weights travel in ``train_model`` for --resume.
    ema_decay: float = 0.0
    # Share of the background grid cells (no target, not next to one) whose rays a training step
    # renders, drawn anew each step; target cells and their neighbours always (pnyolo.components.ray_selection).
    # 1: every ray (the paper). Kinds that cast no rays (single-view, bev) refuse other values.
    background_rays: float = 1.0
    # Share of a step's rendered rays whose own (target) view's image features are withheld, so they
    # must find their road users from the other source views, as for a road user hidden in its view.
    # Cells of road users no other source view sees are never drawn. 0: off (the paper). Models
    # that cast no rays (single-view, bev) refuse other values (pnyolo.components.ray_selection).
    own_view_dropout: float = 0.0
    # TensorBoard event files in OUT/tensorboard (pnyolo.engine.logs.TensorBoardLog): every loss term,
    # the learning rate, step time, validation metrics and a few validation pictures.
    tensorboard: bool = True


@dataclass(frozen=True)
class EvalConfig:
    """How a model's outputs are decoded and scored: its operating point (a value: a chooser returns a new one with
    ``dataclasses.replace``, nothing writes into it after loading)."""

    conf_threshold: float = 0.45  # detections scoring below this are dropped
    nms_iou: float = 0.75  # NMS: a box overlapping a higher-scoring one by more than this IoU goes
    # Depth-gated NMS (metres): boxes whose distance estimates differ by more than this do not suppress
    # each other, so a road user hidden behind another survives its occluder's box. None: plain NMS.
    depth_gap: float | None = None
    # Depth peaks (pixelnerf-yolo): up to this many candidates per ray and anchor, at confidence
    # peaks at least peak_gap metres apart, each decoded as a detection (1: the paper's one box).
    depth_peaks: int = 1
    peak_gap: float = 2.0  # depth_peaks: metres between two peaks along a ray
    match_ious: list[float] = field(default_factory=lambda: [0.1, 0.2, 0.3, 0.4, 0.5, 0.6])  # IoUs metrics are given at
    select_iou: float = 0.4  # F1 at this match IoU picks the best checkpoint
    views: list[int] | None = None  # camera indices for evaluation (None: the first num_views)
    # World-frame detections (bev, late fusion, lifted 2D detections): same-class detections whose
    # ground-plane centres lie closer than this (metres) are one road user (the lower score goes).
    centre_nms_m: float = 1.0
    # Late fusion: each car sends its detections scoring at least late_send (None: conf_threshold). With
    # late_keep, the rule is agreement (pnyolo.cooperation.agreement): the cars' reports of one road user are
    # scored together by noisy-OR and kept from late_keep on; None: the best-scoring car's detection is kept.
    late_send: float | None = None  # late fusion: cars send detections from this score on (None: conf_threshold)
    late_keep: float | None = None  # late fusion by agreement: noisy-OR scores kept from here (None: best car)
    # Late fusion: each received detection's score s, seen at d metres from its sender's camera, replaced by
    # sigmoid(a * logit(s) + b * d / 10 + c) before pooling (pnyolo.cooperation.calibration; chosen on validation).
    late_calibration: list[float] | None = None  # late fusion: [a, b, c] of the sender calibration (None: raw)


@dataclass
class Config:
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=lambda: config_class(DEFAULT_KIND)())  # the class of model.kind
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)


def to_dict(cfg) -> dict:
    return dataclasses.asdict(cfg)


def _from_dict(cls, obj: Any, where: str):
    if not isinstance(obj, dict):
        raise UserError(f"config {where or 'top level'}: expected a mapping, got {type(obj).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(obj) - set(fields))
    if unknown:
        raise UserError(f"config {where or 'top level'}: unknown key(s) {excerpt(unknown)}; known: {sorted(fields)}")
    kwargs = {}
    hints = {f.name: f.type for f in dataclasses.fields(cls)}
    for name, value in obj.items():
        default = getattr(cls(), name)
        sub = f"{where}.{name}" if where else name
        if cls is Config and name == "model":
            kwargs[name] = _from_dict(_model_class(value), value, sub)
        elif dataclasses.is_dataclass(default):
            kwargs[name] = _from_dict(type(default), value, sub)
        else:
            kwargs[name] = _coerce(value, default, hints[name], sub)
    return cls(**kwargs)


def _coerce(value, default, hint, where):
    allows_none = "None" in str(hint)
    if value is None:
        if allows_none:
            return None
        raise UserError(f"config {where}: must not be null")
    if isinstance(default, bool) or "bool" == str(hint):
        if not isinstance(value, bool):
            raise UserError(f"config {where}: expected true/false, got {excerpt(value)}")
        return value
    if isinstance(default, float) or str(hint) == "float":
        if isinstance(value, str):  # YAML 1.1 reads "1e-3" (no dot) as a string
            try:
                value = float(value)
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise UserError(f"config {where}: expected a number, got {excerpt(value)}")
        return float(value)
    if isinstance(default, int) or str(hint) == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise UserError(f"config {where}: expected an integer, got {excerpt(value)}")
        return value
    if isinstance(default, str) or str(hint).startswith("str"):
        if not isinstance(value, str):
            raise UserError(f"config {where}: expected a string, got {excerpt(value)}")
        return value
    if "list" in str(hint):
        if not isinstance(value, list):
            raise UserError(f"config {where}: expected a list, got {excerpt(value)}")
        return value
    return value


def _unknown_for_kind(obj: dict, overrides: list[str]) -> None:
    """An override of a key that the chosen kind lacks but another kind has: a one-line error saying so."""
    model = obj.get("model") if isinstance(obj.get("model"), dict) else {}
    cls = _model_class(model)
    for item in overrides or []:
        parts = item.split("=", 1)[0].strip().split(".")
        if len(parts) < 2 or parts[0] != "model":
            continue
        mine = cls()
        depth = next((d for d in range(2, len(parts) + 1) if not has_path(mine, parts[1:d])), None)  # first missing
        owners = _owners(parts[1:depth]) if depth else []
        if owners:
            raise UserError(f"--set {item}: model.kind {model.get('kind', DEFAULT_KIND)} has no "
                            f"{'.'.join(parts[:depth])} (that is {' and '.join(owners)}'s)")


def someone_elses_key(kind: str, key: str) -> bool:
    """Whether the dotted config ``key`` (``model.loss.iou``) is a model key that ``kind`` lacks and another
    registered kind has (a shared setting that is theirs; a key no kind has is nobody's, to be refused)."""
    parts = key.split(".")
    if parts[0] != "model" or len(parts) < 2 or has_path(config_class(kind)(), parts[1:]):
        return False
    return bool(_owners(parts[1:]))


def _owners(path: list[str]) -> list[str]:
    """The registered kinds whose model section has the key ``path`` (parts below ``model.``)."""
    return [k for k, c in kinds().items() if has_path(c.config_class(), path)]


def from_dict(obj: dict) -> Config:
    check_expansion(obj, "config")  # a checkpoint's config may share references as YAML aliases do
    return _from_dict(Config, obj or {}, "")


def apply_overrides(obj: dict, overrides: list[str]) -> dict:
    """Apply ``section.key=value`` strings (values parsed as YAML) to a nested dict."""
    for item in overrides or []:
        if "=" not in item:
            raise UserError(f"--set {excerpt(item)}: expected key=value")
        key, raw = item.split("=", 1)
        try:
            value = yaml.safe_load(raw) if raw.strip() else ""
        except yaml.YAMLError as exc:
            raise UserError(f"--set {excerpt(item)}: value is not valid YAML ({exc.__class__.__name__})") from None
        check_expansion(value, f"--set {excerpt(key)}")
        node = obj
        parts = key.strip().split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise UserError(f"--set {excerpt(item)}: {p} is not a section")
        node[parts[-1]] = value
    return obj


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Defaults <- YAML file <- ``--set`` overrides; validated."""
    obj: dict = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise UserError(f"config file {path} does not exist")
        try:
            obj = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise UserError(f"config file {path}: invalid YAML ({exc.__class__.__name__})") from None
        if not isinstance(obj, dict):
            raise UserError(f"config file {path}: expected a mapping of sections (data:, model:, ...), "
                            f"got a {type(obj).__name__}")
        check_expansion(obj, f"config file {path}")
    kind = next((yaml.safe_load(o.split("=", 1)[1]) for o in reversed(overrides or [])
                 if o.split("=", 1)[0].strip() == "model.kind" and "=" in o), None)
    if kind is not None and isinstance(obj.get("model", {}), dict):  # the file's sections are kept or left by the
        obj["model"] = {**obj.get("model", {}), "kind": kind}          # kind the run uses
    obj = upgrade_legacy(obj, say=True)
    overrides = moved_loss_overrides(obj, overrides or [])  # --set loss.KEY: the kind's model.loss.KEY, which it wins
    obj = apply_overrides(obj, overrides)
    _unknown_for_kind(obj, overrides)
    cfg = from_dict(obj)
    validate(cfg)
    return cfg


def model_signature(cfg: Config) -> dict:
    """The model keys a checkpoint's config must match to resume it or load its weights (``ModelConfig.signature``)."""
    return cfg.model.signature()
