"""Benchmark presets as data: one YAML file each, loaded and validated here.

    preset = load_preset("cpu")                    # configs/bench/cpu.yaml
    preset = load_preset("my_bench.yaml")          # a user's own file
    preset.train, preset.config_path, preset.overrides_for(kind)

A preset file holds the fields of ``BenchPreset``; ``splits`` gives the scenarios of each split,
either as a list of names or as ``{layouts: [...], redraws: K, new_layouts: N}`` (each layout and its redrawn
variants ``NAME-s1`` ... ``NAME-sK``; validation and test may add N procedural layouts never trained on, one draw
each: ``pnyolo.bench.new_layouts``). ``config`` is resolved against the preset file's folder.
``base: NAME`` (a built-in preset or a file beside this one) takes every key this file does not give
from that preset. Unknown keys and wrong types are one-line user errors.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path

import yaml

from dataset_spec.cli_support import UserError
from dataset_spec.names import excerpt
from pnyolo.bench.preset_checks import check_places, check_render_options
from pnyolo.bench.new_layouts import BUILT_IN, FIRST, NEW, by_test_set, is_new_layout, new_layout_names
from pnyolo.bench.state_targets import check_state_targets
from pnyolo.config.checks import check_expansion
from pnyolo.registry import kinds, model_class

REPO = Path(__file__).resolve().parents[2]
PRESET_DIR = REPO / "configs" / "bench"
SPLITS = ("train", "val", "test")
MAX_REDRAWS, MAX_SCENARIOS = 1000, 10000  # every count a preset declares is bounded (a split's draws, its scenarios)


def multi_view_kinds(names) -> list[str]:
    """The model kinds among ``names`` (other names ignored) that read the other source views, in order."""
    return [k for k in names if k in kinds() and model_class(k).reads_other_views]


@dataclass
class BenchPreset:
    name: str
    description: str
    train: list[str]
    val: list[str]
    test: list[str]
    render: list[str]  # blender-gen render options (quality / resolution / samples)
    hdr: str = "all"
    config: str = "configs/cpu.yaml"  # the base config file (relative: to the repository)
    models: list[str] = field(default_factory=list)  # the kinds trained with the same budget, in this order
    # The roles the report's comparisons and targets are stated for (kinds among ``models``; '': none):
    primary: str = ""  # the model the headline targets are stated for (hidden-but-seen recall, F1 over baseline)
    baseline: str = ""  # the one-camera floor every multi-view model and fusion is compared with
    fusion: list[str] = field(default_factory=list)  # two models whose detections are also scored together
    # the kind whose cars' 3D detections late fusion into the baseline pools ('' or not in a run: the first of the
    # run's models with 3D detections)
    late_sender: str = ""
    overrides: list[str] = field(default_factory=list)  # --set values for both models
    # --set values for one model only (by model.kind), after ``overrides``: a choice made for that model on validation
    model_overrides: dict[str, list[str]] = field(default_factory=dict)
    steps: int = 600  # optimizer steps per model: the shared training budget
    max_distance: float | None = 40.0  # ground truth: road users up to this far from the camera (both models)
    anchors: int = 3  # YOLO anchors fitted to the training labels (0: keep the config's)
    # the match IoU at which operating points are chosen, models compared and targets stated (one of eval.match_ious)
    select_iou: float = 0.2
    conf_grid: tuple[float, ...] = (0.1, 0.2, 0.3, 0.45, 0.6, 0.75, 0.85, 0.9)  # confidence thresholds tried on validation
    nms_grid: tuple[float, ...] = (0.45, 0.3, 0.2)  # NMS IoU thresholds tried on validation
    # depth-gated NMS gaps (metres; None: plain NMS) tried on validation for models with distance estimates
    depth_gaps: tuple[float | None, ...] = (None,)
    # depth peaks per ray and anchor (eval.depth_peaks) tried on validation for models that render rays
    depth_peaks: tuple[int, ...] = (1,)
    # validation and test score every camera of each scenario once, in items of data.num_views cameras
    # (data.camera_groups); False: the first data.num_views cameras of each scenario only
    every_camera: bool = True
    # the hidden-but-seen recall of the report's extra operating point (for information; the PASS/FAIL targets ask
    # for recall above the baseline's, which is chance: pnyolo.bench.targets.CHANCE_MARGIN)
    hidden_recall_target: float = 0.5
    time_budget_s: float | None = None  # a target: the run with the dataset cached within this (null: none)
    # sigmas (metres and degrees together) of the test-time pose-noise sweep (pnyolo.bench.robustness; empty: none)
    pose_noise_sweep: tuple[float, ...] = ()
    # delays (ms) of the other cars' messages swept on test sequences (pnyolo.bench.time_axis; empty: none)
    delay_sweep: tuple[float, ...] = ()
    tracking: bool = False  # track each model with 3D detections over the test sequences (MOTA, IDF1)
    examples: int = 6
    needs_gpu: bool = False  # sized for a GPU: refused on a machine without one unless --device cpu is asked for
    # blender-gen options of one split's scenarios after ``render`` and ``hdr`` (the later option wins), e.g.
    # ``train: [--frames, "5", --fps, "2", --hdr, "noon,dusk"]``: that split rendered as sequences
    split_render: dict[str, list[str]] = field(default_factory=dict)
    # blender-gen options of the new layouts (``splits.val/test.new_layouts``) after ``render`` and ``hdr``, instead of
    # their split's: one draw each under one lighting drawn by its name, a frame each
    new_layouts_render: list[str] = field(default_factory=lambda: ["--hdr", "random"])
    # targets on the 3D state and the tracks of each model with 3D detections (``pnyolo.bench.state_targets``)
    state_targets: dict[str, float] = field(default_factory=dict)

    def render_groups(self) -> list[tuple[str, list[str], list[str]]]:
        """(split, scenarios, blender-gen options after ``render`` and ``hdr``) of each render call: a split's
        built-in layouts with its ``split_render``, its new layouts with ``new_layouts_render``."""
        groups = []
        for split in SPLITS:
            sets = by_test_set(getattr(self, split))
            groups += [(split, sets[name], [*extra, "--split", split]) for name, extra in
                       ((BUILT_IN, self.split_render.get(split, [])), (NEW, self.new_layouts_render)) if name in sets]
        return groups

    @property
    def config_path(self) -> Path:
        """The base config file: relative to the repository (pathlib keeps an absolute one as it is)."""
        return REPO / self.config

    @property
    def iou(self) -> str:
        """``select_iou`` as the summaries' keys spell it ("0.2")."""
        return f"{self.select_iou:g}"

    @property
    def multi_view(self) -> tuple[str, ...]:
        """The models that read the other source views (own-view ablation, coverage)."""
        return tuple(multi_view_kinds(self.models))

    @property
    def late_fusion(self) -> tuple[str, ...]:
        """The models with 3D detections, also scored by late fusion."""
        return tuple(k for k in self.models if model_class(k).world_outputs)

    @property
    def scenarios(self) -> list[str]:
        return self.train + self.val + self.test

    def overrides_for(self, kind: str) -> list[str]:
        """The config overrides one model trains with: the shared ones but the model keys only other kinds have
        (``model.loss.iou`` is the YOLO kinds'), then its own."""
        from pnyolo.config import someone_elses_key

        shared = [o for o in self.overrides if not someone_elses_key(kind, o.split("=", 1)[0].strip())]
        return [*shared, *self.model_overrides.get(kind, [])]

    def scored_text(self, num_views: int) -> str:
        """Which cameras validation and test score, for the report and the log."""
        if self.every_camera:
            return (f"every camera of each scenario scored once, in items of {num_views} cameras (the other "
                    f"{num_views - 1} its source views; a short last group completed with cameras from the start, "
                    "there as source views only)")
        return f"the first {num_views} cameras of each scenario scored, each the others' source views"

    def config_text(self) -> str:
        """The overrides as ``--set`` options, for the report."""
        text = " ".join("--set " + o for o in self.overrides)
        for kind, sets in self.model_overrides.items():
            if sets:
                text += f"; {kind} only: " + " ".join("--set " + o for o in sets)
        return text


def builtin_presets() -> list[str]:
    """The names of the presets shipped in ``configs/bench``."""
    return sorted(p.stem for p in PRESET_DIR.glob("*.yaml"))


def redrawn(layouts: list[str], times: int) -> list[str]:
    """``layouts`` and their variants ``NAME-s1`` ... ``NAME-sTIMES`` (the same layouts, every road
    user, camera and building drawn again): more scenes to learn from, no held-out layout seen."""
    return list(layouts) + [f"{n}-s{k}" for k in range(1, times + 1) for n in layouts]


def preset_path(name_or_path: str | Path) -> Path:
    """A built-in preset's file (``cpu``) or a user's YAML file (any path ending .yaml/.yml)."""
    text = str(name_or_path)
    if text.endswith((".yaml", ".yml")) or "/" in text:
        path = Path(text)
        if not path.is_file():
            raise UserError(f"benchmark preset file {path} does not exist")
        return path
    path = PRESET_DIR / f"{text}.yaml"
    if not path.is_file():
        raise UserError(f"unknown benchmark preset {excerpt(text)}; built in: {', '.join(builtin_presets())} "
                        "(or give a preset file, e.g. configs/bench/cpu.yaml)")
    return path


def load_preset(name_or_path: str | Path) -> BenchPreset:
    """Read and validate one preset file (see the module docstring)."""
    path = preset_path(name_or_path)
    return preset_from_dict(_read(path, ()), path)


def _read(path: Path, chain: tuple[Path, ...]) -> dict:
    """One preset file's keys over those of the preset it names as ``base`` (each key replaced whole),
    with ``config`` made absolute so it stays relative to the file that gave it."""
    where = f"benchmark preset {path}"
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise UserError(f"{where}: invalid YAML ({exc.__class__.__name__})") from None
    if not isinstance(raw, dict):
        raise UserError(f"{where}: expected a mapping at the top level")
    check_expansion(raw, where)
    if isinstance(raw.get("config"), str):
        raw["config"] = str((path.parent / raw["config"]).resolve())
    if "base" not in raw:
        return raw
    base = raw.pop("base")
    if not isinstance(base, str) or not base:
        raise UserError(f"{where}: base must name a preset (e.g. cpu) or a preset file")
    base_path = preset_path(path.parent / base if base.endswith((".yaml", ".yml")) or "/" in base else base)
    if not (base_path.resolve().is_relative_to(path.parent.resolve()) or base_path.resolve().parent == PRESET_DIR):
        raise UserError(f"{where}: base {excerpt(base)} is neither a built-in preset nor a file in the preset's folder")
    chain = (*chain, path.resolve())
    if base_path.resolve() in chain:
        raise UserError(f"{where}: base {base} leads back to itself")
    inherited = _read(base_path, chain)
    inherited.pop("name", None)  # a preset's name is its own
    return {**inherited, **raw}


def preset_from_dict(raw: dict, path: Path) -> BenchPreset:
    where = f"benchmark preset {path}"
    if not isinstance(raw, dict):
        raise UserError(f"{where}: expected a mapping at the top level")
    known = {f.name for f in fields(BenchPreset)} - set(SPLITS) | {"splits"}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise UserError(f"{where}: unknown key(s) {excerpt(unknown)}; known: {sorted(known)}")
    for key in ("description", "splits", "render"):
        if key not in raw:
            raise UserError(f"{where}: missing key {key!r}")
    values = {"name": raw.get("name", path.stem)}
    splits = raw["splits"]
    if not isinstance(splits, dict) or sorted(splits) != sorted(SPLITS):
        raise UserError(f"{where}: splits must give exactly {', '.join(SPLITS)}")
    for split in SPLITS:
        values[split] = _split(splits[split], f"{where}: splits.{split}", split)
    defaults = BenchPreset("", "", [], [], [], [])
    for f in fields(BenchPreset):
        if f.name in raw and f.name not in ("name", *SPLITS):
            values[f.name] = _value(raw[f.name], getattr(defaults, f.name), f.name, where)
    if "config" in values:  # relative to the preset file, stored relative to the repository when inside it
        config = (path.parent / values["config"]).resolve()
        if not (config.is_relative_to(path.parent.resolve()) or config.is_relative_to(REPO / "configs")):
            raise UserError(f"{where}: config {excerpt(values['config'])} is outside the preset's folder and the "
                            "project's configs/ (a preset reads no other file)")
        if not config.is_file():
            raise UserError(f"{where}: config {values['config']} ({config}) does not exist")
        values["config"] = str(config.relative_to(REPO)) if config.is_relative_to(REPO) else str(config)
    preset = BenchPreset(**values)
    _check(preset, where)
    return preset


def _split(value, where: str, split: str) -> list[str]:
    if isinstance(value, dict):
        unknown = sorted(set(value) - {"layouts", "redraws", "new_layouts"})
        if unknown or not ("layouts" in value or value.get("new_layouts")):
            raise UserError(f"{where}: a list of scenario names or {{layouts: [...], redraws: K, new_layouts: N}}")
        times, new = value.get("redraws", 0), value.get("new_layouts", 0)
        for key, count in (("redraws", times), ("new_layouts", new)):
            if isinstance(count, bool) or not isinstance(count, int) or not 0 <= count <= MAX_REDRAWS:
                raise UserError(f"{where}.{key}: a whole number in 0..{MAX_REDRAWS}, got {excerpt(count)}")
        if new and split not in FIRST:
            raise UserError(f"{where}.new_layouts: new layouts are held out, for {' and '.join(FIRST)} only")
        layouts = _names(value["layouts"], where + ".layouts") if "layouts" in value else []
        if len(layouts) * (times + 1) + new > MAX_SCENARIOS:  # checked before the list is built
            raise UserError(f"{where}: {len(layouts)} layouts x {times + 1} draws and {new} new layouts, more than "
                            f"{MAX_SCENARIOS} scenarios")
        return redrawn(layouts, times) + new_layout_names(split, new)
    return _names(value, where)


def _names(value, where: str) -> list[str]:
    if not isinstance(value, list) or not value or not all(isinstance(v, str) and v for v in value):
        raise UserError(f"{where}: a non-empty list of scenario names")
    if len(value) > MAX_SCENARIOS:
        raise UserError(f"{where}: {len(value)} scenarios, more than {MAX_SCENARIOS}")
    return list(value)


def _value(value, default, name: str, where: str):
    """``value`` checked against the type of the field's default (tuples come from YAML lists)."""
    if name == "state_targets":
        return check_state_targets(value, where)
    if isinstance(default, bool):
        ok = isinstance(value, bool)
    elif isinstance(default, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif isinstance(default, float):
        nullable = name in ("max_distance", "time_budget_s")  # null: no limit
        ok = (value is None and nullable) or (isinstance(value, (int, float)) and not isinstance(value, bool))
        value = float(value) if ok and value is not None else value
    elif isinstance(default, str):
        ok = isinstance(value, str)
    elif isinstance(default, tuple):
        ok = isinstance(value, list) and all(v is None or (isinstance(v, (int, float)) and not isinstance(v, bool))
                                             for v in value) and (bool(value) or not default)  # () may stay off
        value = tuple(value) if ok else value
    elif isinstance(default, list):
        ok = isinstance(value, list) and all(isinstance(v, str) for v in value)
    elif isinstance(default, dict):
        ok = isinstance(value, dict) and all(isinstance(v, list) and all(isinstance(x, str) for x in v)
                                             for v in value.values())
    else:
        ok = True
    if not ok:
        raise UserError(f"{where}: {name}: {excerpt(value)} has the wrong type (expected like {default!r})")
    return value


def _check(preset: BenchPreset, where: str) -> None:
    """Ranges and relations no single field's type states."""
    if preset.steps < 1:
        raise UserError(f"{where}: steps must be >= 1, got {preset.steps}")
    if preset.anchors < 0 or preset.examples < 0:
        raise UserError(f"{where}: anchors and examples must be >= 0")
    for key, options in [("render", preset.render), ("hdr", ["--hdr", preset.hdr]),
                         *((f"split_render.{k}", v) for k, v in preset.split_render.items()),
                         ("new_layouts_render", preset.new_layouts_render)]:
        check_render_options(options, f"{where}: {key}")
    unknown = sorted(set(preset.split_render) - set(SPLITS))
    if unknown:
        raise UserError(f"{where}: split_render names splits {excerpt(unknown)}; splits are {', '.join(SPLITS)}")
    if preset.max_distance is not None and preset.max_distance <= 0:
        raise UserError(f"{where}: max_distance must be > 0 metres (or null: no limit)")
    if not all(0 < t < 1 for t in preset.conf_grid) or not all(0 < t < 1 for t in preset.nms_grid):
        raise UserError(f"{where}: conf_grid and nms_grid hold thresholds in (0, 1)")
    if not all(g is None or g > 0 for g in preset.depth_gaps):
        raise UserError(f"{where}: depth_gaps hold metres > 0 or null (plain NMS)")
    if not all(isinstance(k, int) and 1 <= k <= 8 for k in preset.depth_peaks):
        raise UserError(f"{where}: depth_peaks hold whole numbers in 1..8")
    if not all(d is not None and d > 0 for d in preset.delay_sweep):
        raise UserError(f"{where}: delay_sweep holds delays > 0 (milliseconds; 0 is always scored beside them)")
    if not all(s is not None and s > 0 for s in preset.pose_noise_sweep):
        raise UserError(f"{where}: pose_noise_sweep holds sigmas > 0 (metres and degrees; 0 is the run itself)")
    if preset.time_budget_s is not None and preset.time_budget_s <= 0:
        raise UserError(f"{where}: time_budget_s must be > 0 seconds (or null: none)")
    if not 0 < preset.select_iou < 1:
        raise UserError(f"{where}: select_iou must be in (0, 1)")
    if not 0 < preset.hidden_recall_target <= 1:
        raise UserError(f"{where}: hidden_recall_target must be in (0, 1]")
    known = sorted(kinds())
    if not preset.models or len(set(preset.models)) != len(preset.models) or not set(preset.models) <= set(known):
        raise UserError(f"{where}: models must list distinct model kinds of {known}, got {preset.models}")
    unknown = sorted(set(preset.model_overrides) - set(known))
    if unknown:
        raise UserError(f"{where}: model_overrides for unknown model kind(s) {unknown}; known: {known}")
    roles = [preset.primary, preset.baseline, preset.late_sender, *preset.fusion]
    if any(r and r not in known for r in roles) or preset.fusion and (len(preset.fusion) != 2
                                                                       or len(set(preset.fusion)) != 2):
        raise UserError(f"{where}: primary, baseline and late_sender name a kind, fusion two kinds, of {known}")
    if preset.late_sender and preset.late_sender not in preset.late_fusion:
        raise UserError(f"{where}: late_sender {preset.late_sender} is not one of the models with 3D detections "
                        f"{list(preset.late_fusion)}")
    check_places(preset, dict.fromkeys([*preset.models, *preset.model_overrides]), where)
    trained_new = [s for s in preset.train if is_new_layout(s)]
    if trained_new:
        raise UserError(f"{where}: splits.train names {excerpt(trained_new)}, of the blocks held out as new layouts "
                        "(procedural-10000 on): training may not see them")
    base = {s: s.split("-s")[0] for s in preset.scenarios}
    for a, b in (("train", "val"), ("train", "test"), ("val", "test")):
        shared = {base[s] for s in getattr(preset, a)} & {base[s] for s in getattr(preset, b)}
        if shared:
            raise UserError(f"{where}: layout(s) {sorted(shared)} in both {a} and {b} (redrawn or not): "
                            "held-out layouts must stay unseen")
