"""One prediction plan and the one runner that carries it out. A plan says which models a comparison scores and
which rows read them (each model, its own-view ablation, its late fusion, two models' fusion, late fusion into an
ego, the sampling coverage, the other cars' pose error); the (model, condition) pairs those rows read follow from
it, and ``predict_plan`` predicts each pair once (``pnyolo.engine.predict``) into the ``Comparison`` evaluation
scores. The bench's test stage builds its plan from the kinds' decodings and the preset; ``pnyolo-eval``,
``pnyolo-track`` and ``pnyolo-predict`` build theirs from the command line's flags: a bench row and its command line are one
computation, not two that agree::

    plan = PredictionPlan.of({k: t.decoding for k, t in trained.items()}, fuse=(primary, baseline))
    comparison = predict_plan(plan, trained, dataset)       # clean, each view alone, samples kept: each once
    accs = evaluate_models(comparison, dataset)             # pnyolo.evaluation.evaluate
    scoring = predict_scoring(trained[kind], dataset, own=True)   # one model's plan: its Scoring

Here, above both the engine and the analyses, so that ``engine`` imports no analysis.
"""
from __future__ import annotations

from dataclasses import dataclass

from pnyolo.cooperation.late_fusion import Channel
from pnyolo.cooperation.pose_noise import PoseNoise
from pnyolo.cooperation.senders import OwnViews
from pnyolo.engine.predict import Condition, Trained, predict
from pnyolo.evaluation.coverage import CoverageAccumulator
from pnyolo.evaluation.evaluate import LATE_FUSION, OWN_VIEW, Comparison, LateInto, Scoring
from pnyolo.models import Decoding

COVERAGE = "coverage"
ROWS = (OWN_VIEW, LATE_FUSION, COVERAGE)  # the rows a kind's capabilities give (PredictionPlan.of)


@dataclass(frozen=True)
class PredictionPlan:
    """What a comparison scores: ``models`` (names, in the order rows show them), the ``own_view`` ablation, the
    ``late`` fusion and the ``coverage`` of some of them, the ``fuse`` pair's union, the late fusion of one sender
    into an ego (``late_into``), the other cars' poses wrong by ``pose_noise`` (the models' clean predictions made
    under it). ``clean`` False: only what the cars send is predicted (each view alone), no row of the models;
    ``peaks``: the clean outputs kept at this many depth peaks (a sweep over fewer decodes them, ``Condition``)."""

    models: tuple[str, ...]
    own_view: tuple[str, ...] = ()
    late: tuple[str, ...] = ()
    fuse: tuple[str, str] | None = None
    coverage: tuple[str, ...] = ()
    late_into: LateInto | None = None
    pose_noise: PoseNoise | None = None
    clean: bool = True
    peaks: int | None = None

    @classmethod
    def of(cls, decodings: dict[str, Decoding], rows: tuple[str, ...] = ROWS, late: tuple[str, ...] | None = None,
           fuse: tuple[str, str] | None = None, late_into: LateInto | None = None,
           pose_noise: PoseNoise | None = None) -> "PredictionPlan":
        """Every model of ``decodings`` (name -> its kind's decoding, in row order) and of ``rows`` what its kind
        gives: the own-view ablation of those that read other views, the late fusion of those with 3D detections
        (``late``: of these instead), the coverage of those multi-view kinds that say where they query."""
        for row in rows:
            if row not in ROWS:
                raise ValueError(f"unknown row {row!r}: one of {ROWS}")
        if late is None:
            late = tuple(k for k, d in decodings.items() if d.world_outputs) if LATE_FUSION in rows else ()
        return cls(tuple(decodings),
                   own_view=tuple(k for k, d in decodings.items() if d.reads_other_views) if OWN_VIEW in rows else (),
                   late=tuple(late), fuse=fuse, late_into=late_into, pose_noise=pose_noise,
                   coverage=tuple(k for k, d in decodings.items() if d.coverage_text and d.reads_other_views)
                   if COVERAGE in rows else ())

    def conditions(self, name: str) -> tuple[Condition, ...]:
        """What ``name``'s rows read, each predicted once: the clean items (under the plan's pose noise, with the
        samples queried where its coverage is measured) and every view alone (its own-view ablation; the cars'
        messages of its late fusion)."""
        sends = name in self.late or (self.late_into is not None and self.late_into.sender == name)
        clean = (Condition(pose_noise=self.pose_noise, samples=name in self.coverage, peaks=self.peaks),) \
            if self.clean else ()
        return clean + ((Condition(own_view=True),) if name in self.own_view or sends else ())

    def check(self) -> None:
        """A row naming a model the plan does not score (a bug, before any item is predicted)."""
        named = set(self.own_view) | set(self.late) | set(self.coverage) | set(self.fuse or ()) | (
            {self.late_into.sender, self.late_into.ego} if self.late_into else set())
        if not named <= set(self.models):
            raise ValueError(f"the plan's rows name {sorted(named - set(self.models))}, not among {list(self.models)}")


@dataclass(frozen=True)
class Backend:
    """What computes the outputs where torch's forward is not the whole story (``engine.predict.predict``):
    ``runner``, an ONNX Runtime runner instead of torch; ``constants``, item -> the rig's precomputed constants."""

    runner: object = None
    constants: object = None


def predict_plan(plan: PredictionPlan, trained: dict[str, Trained], dataset, device=None, progress: bool = False,
                 senders=None, backend: Backend = Backend()) -> Comparison:
    """Each (model, condition) ``plan`` reads predicted once on ``dataset`` at the model's operating point, as the
    ``Comparison`` its rows score. ``senders``: the dataset the cars' messages come from (each view alone) where
    it is not ``dataset`` (the whole sequences, without the delay the scored items have); ``backend``: what runs
    the models (torch by default)."""
    plan.check()
    if senders is not None and plan.own_view:
        raise ValueError("an own-view ablation is scored on the items themselves, not on another senders' dataset")
    scorings = {}
    for name in plan.models:
        t = trained[name]
        made = {c.own_view: predict(t.model, senders if c.own_view and senders is not None else dataset,
                                    t.config.eval, c, device, backend.runner, progress, backend.constants)
                for c in plan.conditions(name)}
        own = made.get(True)
        scorings[name] = Scoring(t.config, made.get(False), own if senders is None else None,
                                 OwnViews(own, t.config.eval) if own is not None and t.decoding.world_outputs else None)
    coverage = {k: CoverageAccumulator(dataset.class_names, stride=trained[k].model.coverage_stride())
                for k in plan.coverage}
    return Comparison(scorings, own_view=plan.own_view, late=plan.late, fuse=plan.fuse, coverage=coverage,
                      channel=Channel(plan.pose_noise), late_into=plan.late_into)


def predict_scoring(t: Trained, dataset, clean: bool = True, own: bool = False, samples: bool = False,
                    device=None, progress: bool = False, backend: Backend = Backend()) -> Scoring:
    """``t``'s predictions on ``dataset`` at its operating point, the plan of one model: ``clean`` (with the
    samples it queried where ``samples``), every view alone where ``own`` (the own-view ablation and, for a kind
    with 3D detections, the cars' messages, ``cooperation.senders.OwnViews``)."""
    name = t.decoding.kind
    plan = PredictionPlan((name,), own_view=(name,) if own else (), coverage=(name,) if samples else (), clean=clean)
    return predict_plan(plan, {name: t}, dataset, device, progress, backend=backend).models[name]
