"""One benchmark run as a typed record: every stage (``pnyolo.bench.stages``, ``selection``) fills in
its part, and the report (``pnyolo.bench.report``) is rendered from it alone::

    run = BenchRun(load_preset("smoke"), Path("out/bench_smoke"), seed=0)
    run.anchors                       # fitted once to the training labels (None: the config's)
    run.models[kind].config           # the config it trained with; .training: steps, seconds, threads
    run.results[name]                 # a Result: its test figures and what each stage measured
    run.results[name].choice          # a Choice: the operating point chosen on validation

A result's ``as_json`` is its entry in report.json: the test metrics and, under fixed keys, what the
stages measured.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from pnyolo.bench.presets import BenchPreset
from pnyolo.config import Config
from pnyolo.evaluation.evaluate import Entry


@dataclass
class ModelRun:
    kind: str
    config: Config  # what it trains with: base config, overrides, fitted anchors, kind and step budget
    training: dict = field(default_factory=dict)  # steps, reused, seconds (or trained_seconds), threads
    checkpoint: Path | None = None  # chosen on validation


@dataclass
class Choice:
    """The operating point chosen on validation: the checkpoint, the encoder's statistics, the
    decoding settings the kind tunes (``Model.tuned``) and the confidence threshold (one-SE rule)."""

    checkpoint: str  # latest.pt | best.pt
    step: int | None
    eval_stats: str
    depth_peaks: int
    nms_iou: float | None  # None: the model is not decoded by 2D NMS
    depth_gap: float | None
    threshold: float  # the one-standard-error choice
    val_f1: float
    best_threshold: float
    best_val_f1: float
    val_f1_se: float
    rule: str
    val_sweep: list[dict]  # every candidate threshold's validation figures

    def as_json(self) -> dict:
        return {"threshold": self.threshold, "val_f1": self.val_f1, "best_threshold": self.best_threshold,
                "best_val_f1": self.best_val_f1, "val_f1_se": self.val_f1_se, "rule": self.rule,
                "checkpoint": self.checkpoint, "step": self.step, "eval_stats": self.eval_stats,
                "depth_peaks": self.depth_peaks, "nms_iou": self.nms_iou, "depth_gap": self.depth_gap,
                "val_sweep": self.val_sweep}


@dataclass
class Result:
    """One row of the report: a model, or what is made of one or two (``entry``), with its test metrics
    (``MetricAccumulator.summary``) and what the stages measured of it."""

    entry: Entry
    metrics: dict
    choice: Choice | None = None
    test_sweep: list[dict] | None = None  # every candidate threshold on test (for information)
    hidden_point: dict | None = None  # the operating point for the hidden-recall target (selection.hidden_target_point)
    inference_ms: float | None = None
    inference_threads: int | None = None
    train_threads: int | None = None
    coverage: dict | None = None
    encoding_ceiling: dict | None = None
    feature_bytes: int | None = None  # late fusion: what a multi-view model reads from another car instead
    pose_noise_sweep: dict | None = None  # {sigma: figures}
    delay_sweep: dict | None = None  # {delay ms: figures}
    tracking: dict | None = None  # motmetrics' overall figures of its tracks on the test sequences
    late_choice: object | None = None  # late fusion: its rule chosen on validation (late_choice.LateChoice)

    @property
    def name(self) -> str:
        return self.entry.name

    def as_json(self) -> dict:
        """This row as report.json and comparison.json hold it."""
        out = dict(self.metrics)
        extra = {"coverage": self.coverage, "test_threshold_sweep": self.test_sweep,
                 "inference_ms": self.inference_ms, "inference_threads": self.inference_threads,
                 "encoding_ceiling": self.encoding_ceiling, "feature_bytes_per_car_frame": self.feature_bytes,
                 "conf_threshold": None if self.choice is None else self.choice.threshold,
                 "selection": None if self.choice is None else self.choice.as_json(),
                 "pose_noise_sweep": self.pose_noise_sweep, "train_threads": self.train_threads,
                 "delay_sweep": self.delay_sweep, "tracking": self.tracking,
                 "late_fusion_selection": None if self.late_choice is None else self.late_choice.as_json()}
        out.update({k: v for k, v in extra.items() if v is not None})
        return out


@dataclass
class BenchRun:
    preset: BenchPreset
    out: Path
    seed: int = 0
    data: Path | None = None  # the dataset folder (default OUT/dataset)
    command: str = ""
    anchors: list | None = None  # fitted to the training labels; None: the config's own
    models: dict[str, ModelRun] = field(default_factory=dict)
    timings: dict = field(default_factory=dict)  # stage -> seconds (a reused training: a dict saying so)
    statistics: dict = field(default_factory=dict)  # the dataset's splits, images, labels, occlusion
    results: dict[str, Result] = field(default_factory=dict)  # row name -> its Result (models, fusion, ablations)
    beside: dict[str, Path] = field(default_factory=dict)  # label -> another run's report.json (its pose-noise rows)
    beside_rows: dict = field(default_factory=dict)  # those runs' pose-noise rows, "NAME (LABEL)" -> sweep, read at the start
    device: object = None  # where validation and test run (a torch device; None: the machine's best, as training)

    def __post_init__(self):
        self.out = Path(self.out)
        self.data = Path(self.data) if self.data else self.out / "dataset"

    @property
    def runs(self) -> Path:
        return self.out / "runs"

    @property
    def report(self) -> Path:
        return self.out / "report"

    @property
    def num_views(self) -> int:
        """Source views per item (every model shares ``data.num_views``)."""
        return next(iter(self.models.values())).config.data.num_views

    def summaries(self) -> dict[str, dict]:
        """Every row as report.json holds it, by name."""
        return {n: r.as_json() for n, r in self.results.items()}
