"""Scoring predictions (``pnyolo.engine.predict``): training's validation, ``pnyolo-eval`` and the bench share
it: same code, same numbers. Nothing here runs a model.

Example::

    preds = predict(model, MultiViewDataset(root, "test", cfg, views=[0, 1, 2]), cfg.eval)   # engine.predict
    acc = score(preds, cfg.eval)                                 # a MetricAccumulator
    write_report(acc.summary(), "out/eval")                      # pnyolo.evaluation.report

    # two detectors on the same items and source views, plus their fusion (the paper's Table 6.11)
    plan = Comparison({"multi-view": Scoring(mv_cfg, mv_preds), "single-view": Scoring(sv_cfg, sv_preds)},
                      fuse=("multi-view", "single-view"))
    accs = evaluate_models(plan, dataset)                        # {Entry: MetricAccumulator}
    write_comparison({e.name: a.summary() for e, a in accs.items()}, "out/compare")

A ``Comparison`` names what is scored on every item: the models, each model's own-view ablation and
late fusion, two models' fusion, the sampling coverage, the other cars' pose error; each reads a model's
``Scoring`` (its predictions under each condition), item by item (``model_detections``,
``derived_detections``). An ``Entry`` is one row of the result (a model, or what is made of one or two),
typed, its display name derived.
"""
from __future__ import annotations

import sys
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from dataset_spec.names import below
from pnyolo.components.renderer import RayOutputs
from pnyolo.config import Config
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.data.item import Item
from pnyolo.data.targets import perfect_raw
from pnyolo.decoding.yolo import decode_outputs
from pnyolo.decoding.world import pool_views
from pnyolo.models import Decoding
from pnyolo.cooperation.late_fusion import Channel, Ego, LateRule, check_late_fusion, late_fusion, sent_bytes
from pnyolo.cooperation.senders import OwnViews
from pnyolo.evaluation.coverage import CoverageAccumulator
from pnyolo.evaluation.fusion import fuse_detections
from pnyolo.evaluation.metrics import HIDDEN_SEEN_ELSEWHERE, MetricAccumulator, ViewGroundTruth, match_strict
from pnyolo.evaluation.pictures import panel, stack_rows, write_png
from pnyolo.evaluation.top_down import SequenceMovie, top_down

if TYPE_CHECKING:  # the type only: an analysis imports nothing that runs a model
    from pnyolo.engine.predict import Predictions

OWN_VIEW, LATE_FUSION, FUSION = "own view only", "late fusion", "fusion"


@dataclass(frozen=True)
class Entry:
    """One row of a comparison: ``model`` itself (``variant`` ""), its ``OWN_VIEW`` ablation or its
    ``LATE_FUSION`` (with ``other``: into the ego model ``other``), or the ``FUSION`` of ``model`` and ``other``."""

    model: str
    variant: str = ""
    other: str = ""

    @property
    def name(self) -> str:
        """The row's name in reports: the model's, "MODEL, own view only", "MODEL, late fusion", "fusion"."""
        if self.variant == FUSION:
            return FUSION
        if self.variant == LATE_FUSION and self.other:
            return f"{self.model}, {LATE_FUSION} into {self.other}"
        return f"{self.model}, {self.variant}" if self.variant else self.model


def own_view_name(model_name: str) -> str:
    """The row name of ``model_name`` evaluated with each view's own image alone."""
    return Entry(model_name, OWN_VIEW).name


def late_fusion_name(model_name: str) -> str:
    """The row name of ``model_name``'s late fusion (each car alone, 3D detections pooled)."""
    return Entry(model_name, LATE_FUSION).name


def late_into_name(model_name: str, ego: str) -> str:
    """The row name of ``model_name``'s late fusion into the ego model ``ego`` (``late_fusion.Ego``)."""
    return Entry(model_name, LATE_FUSION, ego).name


@dataclass(frozen=True)
class LateInto:
    """Late fusion into an ego model: the ``sender`` model's other cars' reports (sent from ``send``) pooled
    into each target view's ``ego`` detections kept from ``ego_threshold`` (at least the ego's own threshold)."""

    sender: str
    ego: str
    send: float
    ego_threshold: float


@dataclass
class Scoring:
    """One model's predictions on the split (each ``Predictions`` of ``pnyolo.engine.predict``, aligned with the
    dataset's items) and the ``config`` they are decoded by: ``clean``, what it detects (under a comparison's
    pose noise: predicted under it); ``own``, every view alone (the own-view ablation); ``cars``, the cars' own
    3D detections by camera and frame (``cooperation.senders.OwnViews``: late fusion's messages)."""

    config: Config
    clean: Predictions | None
    own: Predictions | None = None
    cars: OwnViews | None = None

    @property
    def decoding(self) -> Decoding:
        return (self.clean if self.clean is not None else self.own).decoding


@dataclass
class Comparison:
    """What ``evaluate_models`` scores on the same items and source views: ``models`` (name -> ``Scoring``,
    each decoding with its own config's thresholds), each of ``own_view`` also with every view alone, each
    of ``late`` (models with 3D detections) by late fusion, the ``fuse`` pair's union after NMS (the first
    model's ``eval.nms_iou`` and ``eval.depth_gap``), the ``coverage`` of some models (name -> accumulator,
    from the clean predictions' samples), and the other cars' poses wrong by ``channel.pose_noise`` as each
    target view's car knows them (the models' clean predictions made under it; the own-view ablations need
    no other car; coverage is measured without noise), their late messages moved to now by
    ``channel.senders``."""

    models: dict[str, Scoring]
    own_view: tuple[str, ...] = ()
    late: tuple[str, ...] = ()
    fuse: tuple[str, str] | None = None
    coverage: dict[str, CoverageAccumulator] = field(default_factory=dict)
    channel: Channel = Channel()  # between the cars: pose noise, late messages moved to now (late_fusion.Channel)
    late_into: LateInto | None = None  # also the late fusion of one sender model into an ego model
    # models whose world detections are also pooled per sample (name -> nuscenes_results.WorldPool), for the
    # devkit's DetectionEval on an export of the split; from the clean predictions, without noise
    pools: dict = field(default_factory=dict)

    def entries(self) -> list[Entry]:
        """Every row, in the order reports show them: the models, the fusion, the ablations, the late fusions."""
        return ([Entry(n) for n in self.models] + ([Entry(self.fuse[0], FUSION, self.fuse[1])] if self.fuse else [])
                + [Entry(n, OWN_VIEW) for n in self.own_view] + [Entry(n, LATE_FUSION) for n in self.late]
                + ([Entry(self.late_into.sender, LATE_FUSION, self.late_into.ego)] if self.late_into else []))

    def check(self) -> None:
        """One-line errors (and bugs) before any item is read."""
        for n in self.late:
            check_late_fusion(self.models[n].decoding)
        if self.late_into is not None:
            if not {self.late_into.sender, self.late_into.ego} <= set(self.models):
                raise ValueError(f"late fusion into {self.late_into.ego}: not among the models {list(self.models)}")
            check_late_fusion(self.models[self.late_into.sender].decoding)
        if self.fuse is not None and not set(self.fuse) <= set(self.models):
            raise ValueError(f"fusion of {self.fuse}: not among the models {list(self.models)}")


@dataclass
class Examples:
    """Pictures of views where the first model finds a ground-truth object the second misses (at the first
    model's ``eval.select_iou``), at most ``count`` of them, into ``folder``."""

    folder: Path
    count: int


def score(preds: Predictions, ev, dataset=None, examples: Examples | None = None, progress: bool = False, ground=None,
          pool=None) -> MetricAccumulator:
    """One model's predictions (``pnyolo.engine.predict.Predictions``) scored, decoded under ``ev``; with the
    ``dataset`` they are of, ``examples`` (pictures of its first items, loaded again with their images),
    ``ground`` (pnyolo.evaluation.ground_moda.GroundRows: each item's world detections) and ``pool``
    (nuscenes_results.WorldPool: each item's outputs); ``progress``: a bar over the items on stderr."""
    decoding = preds.decoding
    class_names = preds.items[0].item.class_names if len(preds) else []
    acc = MetricAccumulator(ev.match_ious, len(class_names), class_names)
    for k in tqdm(range(len(preds)), desc="scoring", unit="item", disable=not progress, file=sys.stderr):
        p, dets = preds.items[k], preds.detections_at(k, ev)
        if ground is not None:
            ground.add(p.item, pool_views(preds.world_at(k, ev, ev.conf_threshold), ev.centre_nms_m),
                       len(dataset.ds.scenario(p.item.scenario).cameras))
        if pool is not None:
            pool.add(p.out, p.item)
        for _, det, gt in scored_views(p.item, dets):
            acc.add(det, gt, p.item.scenario)
        if examples is not None and k < examples.count:
            item = dataset[k]
            write_png(below(examples.folder, f"{item_name(item)}.png"),
                      panel(item, dets, class_names, decoding.targets(item)))
    return acc


@dataclass(frozen=True)
class EncodingCeiling:
    """What a perfect detector decoded like a model finds (``encoding_ceiling``)."""

    match_iou: float
    nms_iou: float
    depth_gap: float | None
    recall: float
    n: int
    breakdown: dict  # ``MetricAccumulator.recall_breakdown``: group -> {recall, n}

    def hidden_seen_recall(self) -> float | None:
        return self.breakdown.get(HIDDEN_SEEN_ELSEWHERE, {}).get("recall")

    def as_json(self) -> dict:
        return asdict(self)


def encoding_ceiling(model, dataset: MultiViewDataset, ev, iou: float = 0.2) -> EncodingCeiling:
    """Recall of a *perfect* detector decoded like a YOLO-grid ``model``: each item's targets
    (``model.targets``) turned back into outputs (``targets.perfect_raw``, exact distances), decoded
    and NMS-ed at ``ev.nms_iou`` (and ``ev.depth_gap``), matched at ``iou``.

    Objects that lose their target slot (several in one cell) or are suppressed by NMS (amodal
    boxes of a hidden object and its occluder overlapping) count as misses: no model trained on
    these targets and decoded this way can exceed this: overall recall and the recall breakdown
    (visibility bins, hidden-but-seen-elsewhere).
    """
    acc = MetricAccumulator((iou,), len(dataset.class_names))
    anchors = model.anchors.cpu()
    for k in range(len(dataset)):
        item = dataset[k]
        out = RayOutputs(**perfect_raw(model.targets(item), anchors, len(dataset.class_names)))
        for _, det, gt in scored_views(item, decode_outputs(out, anchors, item.grid, 0.5, ev.nms_iou, ev.depth_gap)):
            acc.add(det, gt)
    counts = acc.counts(iou)
    return EncodingCeiling(match_iou=iou, nms_iou=ev.nms_iou, depth_gap=ev.depth_gap, recall=counts["recall"],
                           n=counts["tp"] + counts["fn"], breakdown=acc.recall_breakdown(iou))


def _ground_truth(gt: ViewGroundTruth, boxes=None, velocities=None) -> ViewGroundTruth:
    """A view's ground truth; with the item's 3D boxes (N, 7) (and ground velocities (N, 2)) also the world boxes,
    centres and velocities of its road users and the centres of those left out of it (for the 3D metrics)."""
    if boxes is None:
        return gt
    rows = np.asarray(gt.object_rows, dtype=np.int64)
    excluded_rows = np.asarray([] if gt.excluded_rows is None else gt.excluded_rows, dtype=np.int64)
    return replace(gt, centres=boxes[rows, :3], world_boxes=boxes[rows], excluded_centres=boxes[excluded_rows, :3],
                   velocities=np.full((len(rows), 2), np.nan) if velocities is None else velocities[rows])


def item_name(item: Item) -> str:
    """SCENARIO_VARIANT_camCAMERAS, e.g. ``intersection_07_dusk_cam3-4-0``: an item's pictures are
    told apart from those of the scene's other camera groups."""
    return f"{item.scenario}_{item.variant}_cam{'-'.join(str(v) for v in item.views)}"


def scored_views(item: Item, dets: list) -> list[tuple[int, object, ViewGroundTruth]]:
    """(view position, its detections, its ground truth) for each view of the item that evaluation
    scores (``item.scored``; a view serving only as a source is left out), ``dets`` one per view."""
    boxes = None if item.boxes_3d is None else item.boxes_3d.numpy().astype(np.float64).reshape(-1, 7)
    velocities = None if item.velocities is None else item.velocities.numpy().astype(np.float64).reshape(-1, 2)
    return [(v, dets[v], _ground_truth(item.gt[v], boxes, velocities)) for v in item.scored]


def spread_over_scenarios(items: list[tuple]) -> list[int]:
    """Indices of dataset items (tuples starting with the scenario), each scenario's first item
    before any second one (stable otherwise): the first few items visited cover the most scenarios."""
    seen: dict[str, int] = {}
    rank = []
    for k, (scenario, *_) in enumerate(items):
        rank.append((seen.get(scenario, 0), k))
        seen[scenario] = seen.get(scenario, 0) + 1
    return [k for _, k in sorted(rank)]


def model_detections(plan: Comparison, k: int, dataset: MultiViewDataset) -> dict[Entry, list]:
    """Each model's detections on item ``k`` (under the plan's pose noise, if any: its predictions' condition);
    the coverage and pools of the models that measure them."""
    dets = {}
    for n, s in plan.models.items():
        dets[Entry(n)] = s.clean.detections_at(k, s.config.eval)
        p = s.clean.items[k]
        if n in plan.pools:
            plan.pools[n].add(p.out, p.item)
        if n in plan.coverage:
            plan.coverage[n].add_points(p.item, s.decoding.coverage_points(p.out, p.item), dataset.instance_maps(p.item))
    return dets


def derived_detections(plan: Comparison, k: int, item: Item, dets: dict[Entry, list]) -> dict[Entry, int]:
    """Adds the own-view ablations, late fusions and the fusion of item ``k`` to ``dets``; returns the bytes
    each late fusion's cars sent."""
    sent = {}
    for n in plan.own_view:
        s = plan.models[n]
        dets[Entry(n, OWN_VIEW)] = s.own.detections_at(k, s.config.eval)
    lates = [(Entry(n, LATE_FUSION), n, LateRule.of(plan.models[n].config.eval), None) for n in plan.late]
    if plan.late_into is not None:
        into = plan.late_into
        ego = Ego(dets[Entry(into.ego)], into.ego_threshold, plan.models[into.ego].config.eval.nms_iou)
        lates.append((Entry(into.sender, LATE_FUSION, into.ego), into.sender,
                      LateRule.of(plan.models[into.sender].config.eval, into.send), ego))
    for entry, n, rule, ego in lates:
        messages = plan.models[n].cars.messages(item, rule.send)
        dets[entry], sent[entry] = late_fusion(messages, item, rule, plan.channel, ego), sent_bytes(messages)
    if plan.fuse is not None:
        a, b = plan.fuse
        ev = plan.models[a].config.eval
        dets[Entry(a, FUSION, b)] = [fuse_detections(x, y, ev.nms_iou, depth_gap=ev.depth_gap)
                                     for x, y in zip(dets[Entry(a)], dets[Entry(b)])]
    return sent


def example_picture(plan: Comparison, item: Item, dets: dict[Entry, list], views, class_names: list[str], load):
    """The first two models' panels of ``item`` (``load()``: it again, with its images) and the frame from above
    (``top_down``, its target the view of the gain) when the first finds a ground-truth object the second
    misses in one of its scored ``views`` (None otherwise)."""
    names = list(plan.models)
    iou = plan.models[names[0]].config.eval.select_iou
    gains = [v for v, first, gt in views
             if (match_strict(first, gt, iou)[1] & ~match_strict(dets[Entry(names[1])][v], gt, iou)[1]).any()]
    if not gains:
        return None
    full = load()
    rows = [panel(full, dets[Entry(n)], class_names, plan.models[n].decoding.targets(full)) for n in names[:2]]
    above = top_down(item, {n: dets[Entry(n)] for n in names}, gains[0], iou)
    return stack_rows(rows, names[:2]), above


def evaluate_models(plan: Comparison, dataset: MultiViewDataset, examples: Examples | None = None,
                    progress: bool = False) -> dict[Entry, MetricAccumulator]:
    """Every entry of ``plan`` scored on ``dataset``'s items, which its predictions are of (``progress``: a bar
    over them on stderr); the late fusions' accumulators say the mean bytes a car sends per frame (``info``)."""
    plan.check()
    names = list(plan.models)
    first_ev = plan.models[names[0]].config.eval
    accs = {e: MetricAccumulator(first_ev.match_ious, len(dataset.class_names), dataset.class_names)
            for e in plan.entries()}
    sent = {e: [0, 0] for e in accs if e.variant == LATE_FUSION}  # bytes, cars
    written, movie = 0, SequenceMovie(first_ev.select_iou)
    order = spread_over_scenarios(dataset.items)  # example pictures from as many streets as possible
    for k in tqdm(order, desc="scoring", unit="item", disable=not progress, file=sys.stderr):
        item = plan.models[names[0]].clean.items[k].item
        dets = model_detections(plan, k, dataset)
        for e, nbytes in derived_detections(plan, k, item, dets).items():
            sent[e][0] += nbytes
            sent[e][1] += len(item.gt)
        views = scored_views(item, dets[Entry(names[0])])  # ground truth built once, for metrics and examples
        for v, _, gt in views:
            for e, acc in accs.items():
                acc.add(dets[e][v], gt, item.scenario)
        if examples is not None and len(names) >= 2 and written < examples.count:
            pictures = example_picture(plan, item, dets, views, dataset.class_names, lambda: dataset[k])
            if pictures is not None:
                stem = f"{item_name(item)}_{names[0]}_vs_{names[1]}"
                write_png(below(examples.folder, f"{stem}.png"), pictures[0])
                write_png(below(examples.folder, f"{stem}_top_down.png"), pictures[1])
                written += 1
        if examples is not None and examples.count > 0:
            scenario = dataset.ds.scenario(item.scenario)
            movie.add(item, {n: dets[Entry(n)] for n in names}, scenario.fps if scenario.frames > 1 else None)
    if examples is not None:
        movie.write(examples.folder)  # the first test sequence from above, animated
    for e, (nbytes, cars) in sent.items():
        accs[e].info["bytes_per_car_frame"] = nbytes / max(cars, 1)
    return accs
