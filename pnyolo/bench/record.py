"""One benchmark run as a typed record: every stage (``pnyolo.bench.stages``, ``selection``) fills in
its part, and the report (``pnyolo.bench.report``) is rendered from it alone::

    run = BenchRun(load_preset("smoke"), Path("out/bench_smoke"), seed=0)
    run.anchors                       # fitted once to the training labels (None: the config's)
    run.models["bev"].config          # the config it trained with; .training: steps, seconds, threads
    run.summaries["bev"]              # its test figures, once selection has run
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from pnyolo.bench.presets import BenchPreset
from pnyolo.config import Config


@dataclass
class ModelRun:
    kind: str
    config: Config  # what it trains with: base config, overrides, fitted anchors, kind and step budget
    training: dict = field(default_factory=dict)  # steps, reused, seconds (or trained_seconds), threads
    checkpoint: Path | None = None  # chosen on validation


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
    summaries: dict[str, dict] = field(default_factory=dict)  # name -> test figures (models, fusion, ablations)
    beside: dict[str, Path] = field(default_factory=dict)  # label -> another run's report.json (its pose-noise rows)

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
