"""One benchmark run as a typed record: every stage (``pnyolo.bench.stages``, ``selection``) fills in
its part, and the report (``pnyolo.bench.report``) is rendered from it alone::

    run = BenchRun(load_preset("smoke"), Path("out/bench_smoke"), seed=0)
    run.anchors                       # fitted once to the training labels (None: the config's)
    run.models[kind].config           # the config it trained with; .training: steps, seconds, threads
    run.results[name]                 # a Result: its test figures and what each stage measured
    run.results[name].choice          # a Choice: the operating point chosen on validation
    run.results[name].figures         # Figures: the test figures the report reads (f1, recall by group, ...)

A result's ``as_json`` is its entry in report.json: the test metrics and, under fixed keys, what the
stages measured. The report reads the typed fields; only the renderers shared with ``pnyolo-eval``
(``pnyolo.evaluation.report``) read the JSON rows.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from functools import cached_property
from pathlib import Path

from pnyolo.bench.presets import BenchPreset
from pnyolo.config import Config
from pnyolo.evaluation.evaluate import EncodingCeiling, Entry
from pnyolo.evaluation.metrics import HIDDEN_SEEN_ELSEWHERE


@dataclass(frozen=True)
class Share:
    """A recall over a group of road users (None where the group is empty) and how many it holds."""

    recall: float | None
    n: int


NO_ONE = Share(None, 0)


@dataclass(frozen=True)
class ViewCeiling:
    """The share of ground truth with any visible pixel in its own view: no one-view detector's recall exceeds it."""

    recall_ceiling: float | None
    n: int
    fully_hidden: int


@dataclass(frozen=True)
class Figures:
    """The test figures of one row that the report and the targets read, typed; made from the row's metrics
    (``MetricAccumulator.summary``, with what a fusion adds to them) by ``Figures.of``."""

    f1: dict[str, float]  # match IoU as the metrics spell it ("0.2") -> F1, strict matching
    recall_by_group: dict[str, dict[str, Share]]  # match IoU -> ground-truth group -> recall
    within_1m: Share | None  # hidden-but-seen recall within 1 m on the ground plane (rows with world boxes)
    distance_error_m: float | None  # mean absolute distance error (rows with distance estimates)
    view_ceiling: ViewCeiling | None
    bytes_per_car_frame: float | None  # late fusion: what a car sends per frame

    @classmethod
    def of(cls, metrics: dict) -> "Figures":
        m3, ceiling = metrics.get("3d"), metrics.get("single_view_ceiling")
        return cls(f1={iou: c["f1"] for iou, c in metrics["strict"].items()},
                   recall_by_group={iou: {g: _share(v) for g, v in groups.items()}
                                    for iou, groups in metrics["recall_by_visibility"].items()},
                   within_1m=_share(m3["recall_within_1m"][HIDDEN_SEEN_ELSEWHERE]) if m3 else None,
                   distance_error_m=metrics.get("distance_error", {}).get("mean_abs_m"),
                   view_ceiling=None if ceiling is None else ViewCeiling(**ceiling),
                   bytes_per_car_frame=metrics.get("bytes_per_car_frame"))

    def recall(self, iou: str, group: str = HIDDEN_SEEN_ELSEWHERE) -> Share:
        """The recall of a ground-truth group at match IoU ``iou`` (hidden-but-seen unless named)."""
        return self.recall_by_group.get(iou, {}).get(group, NO_ONE)


def _share(row: dict) -> Share:
    return Share(row["recall"], row["n"])


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
    val_layouts: int | None = None  # the validation layouts the standard error resampled (1: none to measure)

    def as_json(self) -> dict:
        return {"threshold": self.threshold, "val_f1": self.val_f1, "best_threshold": self.best_threshold,
                "best_val_f1": self.best_val_f1, "val_f1_se": self.val_f1_se, "val_layouts": self.val_layouts,
                "rule": self.rule,
                "checkpoint": self.checkpoint, "step": self.step, "eval_stats": self.eval_stats,
                "depth_peaks": self.depth_peaks, "nms_iou": self.nms_iou, "depth_gap": self.depth_gap,
                "val_sweep": self.val_sweep}


@dataclass(frozen=True)
class HiddenPoint:
    """The operating point for a hidden-but-seen recall target (``selection.hidden_target_point``): its threshold
    chosen on validation (None: no candidate reaches the target) and the figures there."""

    target: float
    threshold: float | None
    best_val_recall: float | None  # the most any candidate reached on validation
    val_f1: float | None = None
    val_hidden_recall: float | None = None
    test_f1: float | None = None
    test_hidden_recall: float | None = None

    def as_json(self) -> dict:
        """As report.json holds it: the figures only where a threshold was chosen."""
        out = asdict(self)
        return out if self.threshold is not None else {k: out[k] for k in ("target", "threshold", "best_val_recall")}


# late fusion's rules (``pnyolo.bench.late_choice``)
BEST_CAR, AGREEMENT, CALIBRATED, INTO_EGO = "best car", "agreement", "calibrated agreement", "into ego"


@dataclass
class LateChoice:
    """Late fusion's rule and thresholds, chosen on validation (``late_choice.choose_late_fusion``)."""

    rule: str  # BEST_CAR | AGREEMENT | CALIBRATED
    send: float  # cars send their detections scoring at least this
    keep: float  # fused detections scoring at least this are kept (BEST_CAR: the send threshold)
    val_f1: float
    val_f1_se: float
    best_car_val_f1: float  # the best-car rule's validation F1 at its own chosen threshold
    val_sweep: list[dict]  # the winning send threshold's rows over the keep thresholds
    calibration: list[float] | None = None  # CALIBRATED: the sender calibration's [a, b, c]
    val_layouts: int | None = None  # the validation layouts the standard error resampled (1: none to measure)

    def as_json(self) -> dict:
        return asdict(self)

    def point(self, ev):
        """``ev`` (an operating point, ``EvalConfig``) with this rule's late_send, late_keep and late_calibration: a
        new value (the best-car rule keeps no late_keep)."""
        return replace(ev, late_send=self.send, late_keep=None if self.rule == BEST_CAR else self.keep,
                       late_calibration=self.calibration)


@dataclass
class IntoChoice:
    """Late fusion into an ego model, chosen on validation (``late_choice.choose_late_into``)."""

    rule: str  # INTO_EGO
    ego: str
    send: float  # the other cars send from this score
    ego_threshold: float  # the ego's own detections kept from this score
    val_f1: float
    ego_val_f1: float  # the ego model alone at its own chosen threshold, on the same items
    val_grid: list[dict]  # every (send, ego threshold) tried: F1, precision, recall

    def as_json(self) -> dict:
        return asdict(self)


@dataclass
class Result:
    """One row of the report: a model, or what is made of one or two (``entry``), with its test metrics
    (``MetricAccumulator.summary``) and what the stages measured of it."""

    entry: Entry
    metrics: dict
    choice: Choice | None = None
    test_sweep: list[dict] | None = None  # every candidate threshold on test (for information)
    hidden_point: HiddenPoint | None = None  # the operating point for the hidden-recall target
    inference_ms: float | None = None
    inference_threads: int | None = None
    train_threads: int | None = None
    coverage: dict | None = None
    encoding_ceiling: EncodingCeiling | None = None
    feature_bytes: int | None = None  # late fusion: what a multi-view model reads from another car instead
    pose_noise_sweep: dict | None = None  # {sigma: figures}
    delay_sweep: dict | None = None  # {delay ms: figures}
    tracking: dict | None = None  # motmetrics' overall figures of its tracks on the test sequences
    late_choice: LateChoice | IntoChoice | None = None  # late fusion: its rule chosen on validation

    @property
    def name(self) -> str:
        return self.entry.name

    @cached_property
    def figures(self) -> Figures:
        """The test figures the report reads, made once (``metrics`` is not changed after the test stage)."""
        return Figures.of(self.metrics)

    def as_json(self) -> dict:
        """This row as report.json and comparison.json hold it."""
        out = dict(self.metrics)
        extra = {"coverage": self.coverage, "test_threshold_sweep": self.test_sweep,
                 "inference_ms": self.inference_ms, "inference_threads": self.inference_threads,
                 "encoding_ceiling": None if self.encoding_ceiling is None else self.encoding_ceiling.as_json(),
                 "feature_bytes_per_car_frame": self.feature_bytes,
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
    # where blender-gen renders, from the command line only (never a preset): --workers N, or --ray ADDRESS; --device
    render_place: tuple[str, ...] = ("--workers", "1")

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
