"""Evaluation shared by training (validation) and ``pnyolo-eval``: same code, same numbers.

Example::

    acc = evaluate_dataset(model, MultiViewDataset(root, "test", cfg, views=[0, 1, 2]), cfg)
    write_report(acc.summary(), "out/eval")                      # pnyolo.evaluation.report

    # two detectors on the same items and source views, plus their fusion (the paper's Table 6.11)
    accs = evaluate_models({"multi-view": (mv, mv_cfg), "single-view": (sv, sv_cfg)}, dataset, fuse=True)
    write_comparison({k: a.summary() for k, a in accs.items()}, "out/compare")
"""
from __future__ import annotations

import sys
from dataset_spec.names import below
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from pnyolo.components.renderer import RayOutputs
from pnyolo.config import Config
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.data.item import Item
from pnyolo.data.targets import perfect_raw
from pnyolo.decoding.yolo import decode_outputs
from pnyolo.evaluation.fusion import fuse_detections
from pnyolo.evaluation.metrics import MetricAccumulator, ViewGroundTruth, match_strict
from pnyolo.evaluation.pictures import panel, stack_rows, write_png
from pnyolo.evaluation.pose_noise import detections_under_noise
from pnyolo.models import predict_item

FUSION = "fusion"


def own_view_name(model_name: str) -> str:
    """The accumulator name of ``model_name`` evaluated with each view's own image alone."""
    return f"{model_name}, own view only"


def late_fusion_name(model_name: str) -> str:
    """The accumulator name of ``model_name``'s late fusion (each car alone, 3D detections pooled)."""
    return f"{model_name}, late fusion"


@torch.no_grad()
def evaluate_dataset(model, dataset: MultiViewDataset, cfg: Config, device="cpu", example_dir: str | Path | None = None,
                     max_examples: int = 0, progress: bool = False, ground=None) -> MetricAccumulator:
    """One model's metrics over ``dataset`` (``progress``: a bar over the items on stderr); ``ground``
    (pnyolo.evaluation.ground_moda.GroundRows) also gets each item's world detections."""
    was_training = model.training
    model.eval()
    acc = MetricAccumulator(cfg.eval.match_ious, len(dataset.class_names), dataset.class_names)
    for k in tqdm(range(len(dataset)), desc="evaluating", unit="item", disable=not progress, file=sys.stderr):
        item = dataset[k]
        out = predict_item(model, item, device)
        dets = model.decode(out, item, cfg.eval)
        if ground is not None:
            ground.add(item, model.world_detections(out, cfg.eval, cfg.eval.conf_threshold)[0],
                       len(dataset.ds.scenario(item.scenario).cameras))
        for _, det, gt in scored_views(item, dets):
            acc.add(det, gt)
        if example_dir is not None and k < max_examples:
            write_png(below(example_dir, f"{item_name(item)}.png"),
                      panel(item, dets, dataset.class_names))
    model.train(was_training)
    return acc


def encoding_ceiling(dataset: MultiViewDataset, anchors: torch.Tensor, nms_iou: float, iou: float = 0.2,
                     depth_gap: float | None = None) -> dict:
    """Recall of a *perfect* detector: each item's YOLO targets turned back into outputs
    (``targets.perfect_raw``, exact distances), decoded and NMS-ed like any model's (``depth_gap``:
    depth-gated NMS), matched at ``iou``.

    Objects that lose their target slot (several in one cell) or are suppressed by NMS (amodal
    boxes of a hidden object and its occluder overlapping) count as misses: no model trained on
    these targets and decoded this way can exceed this. Returns overall recall and the recall
    breakdown (visibility bins, hidden-but-seen-elsewhere).
    """
    acc = MetricAccumulator((iou,), len(dataset.class_names))
    for k in range(len(dataset)):
        item = dataset[k]
        out = RayOutputs(**perfect_raw(item.targets, anchors.cpu(), len(dataset.class_names)))
        for _, det, gt in scored_views(item, decode_outputs(out, anchors.cpu(), item.grid, 0.5, nms_iou, depth_gap)):
            acc.add(det, gt)
    counts = acc.counts(iou)
    return {"match_iou": iou, "nms_iou": nms_iou, "depth_gap": depth_gap, "recall": counts["recall"],
            "n": counts["tp"] + counts["fn"], "breakdown": acc.recall_breakdown(iou)}


def _ground_truth(gt: ViewGroundTruth, box_centres=None) -> ViewGroundTruth:
    """A view's ground truth; with the item's 3D box centres (N, 3) also the world centres of its
    road users and of those left out of it (for the 3D metrics)."""
    if box_centres is None:
        return gt
    excluded_rows = [] if gt.excluded_rows is None else gt.excluded_rows
    return replace(gt, centres=box_centres[np.asarray(gt.object_rows, dtype=np.int64)],
                   excluded_centres=box_centres[np.asarray(excluded_rows, dtype=np.int64)])


def item_name(item: Item) -> str:
    """SCENARIO_VARIANT_camCAMERAS, e.g. ``intersection_07_dusk_cam3-4-0``: an item's pictures are
    told apart from those of the scene's other camera groups."""
    return f"{item.scenario}_{item.variant}_cam{'-'.join(str(v) for v in item.views)}"


def scored_views(item: Item, dets: list) -> list[tuple[int, object, ViewGroundTruth]]:
    """(view position, its detections, its ground truth) for each view of the item that evaluation
    scores (``item.scored``; a view serving only as a source is left out), ``dets`` one per view."""
    boxes = item.boxes_3d
    centres = None if boxes is None else boxes.numpy().astype(np.float64).reshape(-1, 7)[:, :3]
    return [(v, dets[v], _ground_truth(item.gt[v], centres)) for v in item.scored]


def spread_over_scenarios(items: list[tuple]) -> list[int]:
    """Indices of dataset items (tuples starting with the scenario), each scenario's first item
    before any second one (stable otherwise): the first few items visited cover the most scenarios."""
    seen: dict[str, int] = {}
    rank = []
    for k, (scenario, *_) in enumerate(items):
        rank.append((seen.get(scenario, 0), k))
        seen[scenario] = seen.get(scenario, 0) + 1
    return [k for _, k in sorted(rank)]


@torch.no_grad()
def evaluate_models(models: dict[str, tuple], dataset: MultiViewDataset, device="cpu", fuse: bool = False,
                    example_dir: str | Path | None = None, max_examples: int = 0,
                    own_view: tuple[str, ...] = (), coverage: dict | None = None,
                    late: tuple[str, ...] = (), progress: bool = False, pose_noise=None
                    ) -> dict[str, MetricAccumulator]:
    """Evaluate several detectors on the same items and source views.

    ``models`` maps a name to ``(model, cfg)``; each model decodes with its own config's thresholds.
    With ``fuse`` a further accumulator ``"fusion"`` holds the union of the first two models'
    detections after NMS at the first model's ``eval.nms_iou`` and ``eval.depth_gap`` (the paper's
    Table 6.11).
    Each model named in ``own_view`` is also evaluated with every view's rays seeing only that
    view's image features (``own_view_name(name)``: what the other source views add).
    With ``example_dir``, writes up to ``max_examples`` panels of views where the first model finds
    a ground-truth object that the second misses (at match IoU ``eval.select_iou`` of the first).
    ``coverage`` maps model names to ``CoverageAccumulator``s to fill with their sampling coverage
    (pnyolo.evaluation.coverage), from the same forward passes. Each model named in ``late`` (a
    model with 3D detections) is also evaluated by late fusion (``late_fusion_name(name)``, its
    ``info`` the mean bytes a car sends per frame; pnyolo.evaluation.late_fusion). ``progress``: a
    bar over the items on stderr. ``pose_noise`` (a ``pnyolo.evaluation.pose_noise.PoseNoise``): every
    model and late fusion see the other cars' poses with that error, as each target view's car knows
    them (the own-view ablations need no other car; coverage is measured without noise).
    """
    from pnyolo.evaluation.late_fusion import check_late_fusion, late_fusion

    for n in late:
        check_late_fusion(models[n][0])
    coverage = coverage or {}
    names = list(models)
    if fuse and len(names) < 2:
        raise ValueError("fusion needs two models")
    first_cfg = models[names[0]][1]
    accs = {n: MetricAccumulator(first_cfg.eval.match_ious, len(dataset.class_names), dataset.class_names)
            for n in [*names, *([FUSION] if fuse else []), *map(own_view_name, own_view),
                      *map(late_fusion_name, late)]}
    sent = {n: [0, 0] for n in late}  # bytes, cars
    direct = [n for n in accs if n != FUSION]  # fed each model's own detections (fusion: the union, below)
    was_training = {n: m.training for n, (m, _) in models.items()}
    for m, _ in models.values():
        m.eval()
    written = 0
    order = spread_over_scenarios(dataset.items)  # example pictures from as many streets as possible
    for k in tqdm(order, desc="evaluating", unit="item", disable=not progress, file=sys.stderr):
        item = dataset[k]
        dets = {}
        for n, (m, cfg) in models.items():
            if pose_noise is not None and pose_noise.active:
                dets[n] = detections_under_noise(m, item, device, cfg.eval, pose_noise)
                continue
            out = predict_item(m, item, device, return_samples=n in coverage)
            dets[n] = m.decode(out, item, cfg.eval)
            if n in coverage:
                coverage[n].add_points(item, m.coverage_points(out, item), dataset.instance_maps(item))
        own_outs = {}  # one own-view pass per model, shared by its ablation and its late fusion
        for n in own_view:
            m, cfg = models[n]
            own_outs[n] = predict_item(m, item, device, own_view_only=True)
            dets[own_view_name(n)] = m.decode(own_outs[n], item, cfg.eval)
        for n in late:
            m, cfg = models[n]
            dets[late_fusion_name(n)], nbytes = late_fusion(m, item, device, cfg.eval, own_view_out=own_outs.get(n),
                                                            pose_noise=pose_noise)
            sent[n][0] += nbytes
            sent[n][1] += len(item.gt)
        views = scored_views(item, dets[names[0]])  # ground truth built once, for metrics and examples
        for v, _, gt in views:
            for n in direct:
                accs[n].add(dets[n][v], gt)
            if fuse:
                accs[FUSION].add(fuse_detections(dets[names[0]][v], dets[names[1]][v], first_cfg.eval.nms_iou,
                                                 depth_gap=first_cfg.eval.depth_gap), gt)
        if example_dir is not None and len(names) >= 2 and written < max_examples:
            iou = first_cfg.eval.select_iou
            gains = [v for v, first, gt in views
                     if (match_strict(first, gt, iou)[1] & ~match_strict(dets[names[1]][v], gt, iou)[1]).any()]
            if gains:
                rows = [panel(item, dets[n], dataset.class_names) for n in names]
                write_png(below(example_dir, f"{item_name(item)}_{names[0]}_vs_{names[1]}.png"),
                          stack_rows(rows, [f"{n}" for n in names]))
                written += 1
    for n, (m, _) in models.items():
        m.train(was_training[n])
    for n, (nbytes, cars) in sent.items():
        accs[late_fusion_name(n)].info["bytes_per_car_frame"] = nbytes / max(cars, 1)
    return accs


