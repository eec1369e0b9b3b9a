"""The benchmark's test stage: every model at the operating point chosen on validation, scored on the test
split with what the preset makes of it, each row a typed ``Result`` in ``run.results``::

    select_and_test(run)      # choose on validation (pnyolo.bench.selection), then score test
    run.results[kind].choice, run.results[late_fusion_name(kind)].metrics

What each model gets comes from its kind (``Model``): the own-view ablation for kinds that read other
views, late fusion for kinds with 3D detections, the sampling coverage for kinds that say where they
query the world, the encoding ceiling for kinds with YOLO-grid targets; the fusion pair, the baseline
and the primary model are the preset's, and the first kind with 3D detections is also late-fused into the
baseline (``late_choice.choose_late_into``).
"""
from __future__ import annotations

from pathlib import Path

import torch

from dataset_spec import Dataset
from pnyolo.bench.late_choice import choose_late_fusion, choose_late_into
from pnyolo.bench.presets import BenchPreset
from pnyolo.bench.record import BenchRun, Result
from pnyolo.bench.robustness import pose_noise_sweep
from pnyolo.bench.selection import (_without_scenario_counts, choose_on_validation, hidden_target_point, inference_ms,
                                    threshold_sweep)
from pnyolo.bench.stages import log
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.evaluation.coverage import CoverageAccumulator
from pnyolo.evaluation.devkit_eval import available as devkit_available
from pnyolo.evaluation.devkit_eval import devkit_detection
from pnyolo.evaluation.evaluate import (Comparison, Entry, Examples, LateInto, encoding_ceiling, evaluate_models,
                                        late_fusion_name, late_into_name)
from pnyolo.evaluation.nuscenes_results import WorldPool
from pnyolo.evaluation.predictions import image_index, read_coco_results, score_results


def select_and_test(run: BenchRun, external: dict[str, Path] | None = None) -> None:
    """Each model's checkpoint, batch-norm statistics, decoding settings and threshold chosen on
    validation, then every model and what the preset makes of them scored on test (``run.results``, the
    example pictures in the report folder). ``external``: other detectors' COCO results on the test split
    (every lighting variant, ids of the COCO export with --variant all), scored beside them."""
    preset = run.preset
    run.report.mkdir(parents=True, exist_ok=True)
    models, chosen, vals = {}, {}, {}
    class_names = Dataset.open(run.data).info.detectable_classes
    for kind in preset.models:
        enc = getattr(run.models[kind].config.model, "encoder", None)
        paths = {"encoder.feature_cache": enc.feature_cache} if enc is not None and enc.feature_cache else None
        models[kind], chosen[kind] = choose_on_validation(preset, run.data, run.runs, kind, class_names, vals, paths,
                                                          run.device)
        run.models[kind].checkpoint = models[kind][0]
    log(f"chosen on the validation split (checkpoint, statistics, NMS IoU and depth gap: best F1@{preset.iou}; threshold: "
        "one-standard-error rule): " + ", ".join(f"{k} {v.checkpoint} ({v.eval_stats} statistics, NMS IoU "
                                                 f"{v.nms_iou or 'none'}, depth gap {v.depth_gap}) at confidence "
                                                 f"{v.threshold:.2f}" for k, v in chosen.items()))
    late = {}
    for kind in preset.late_fusion:  # the late-fusion rule, chosen on validation like the models
        (_, m, c) = models[kind]
        late[kind] = choose_late_fusion(preset, m, c, vals[(c.data.image_scale, c.data.cell_px)])
    groups = _by_grid(models)
    tests = {key: MultiViewDataset(run.data, "test", models[kinds[0]][2], training=False,
                                   every_camera=preset.every_camera) for key, kinds in groups.items()}
    test_of = {k: tests[key] for key, kinds in groups.items() for k in kinds}
    into, into_choice = None, None
    sender, ego = next(iter(preset.late_fusion), None), preset.baseline
    if sender and ego in models and ego != sender and test_of[sender] is test_of[ego]:
        c = models[sender][2]
        into_choice = choose_late_into(preset, models[sender][1:], models[ego][1:], ego,
                                       vals[(c.data.image_scale, c.data.cell_px)])
        into = LateInto(sender, ego, into_choice.send, into_choice.ego_threshold)
    log(f"evaluate: {len(next(iter(tests.values())))} test items, "
        f"{preset.scored_text(next(iter(models.values()))[2].data.num_views)}")
    fuse = tuple(preset.fusion) if (set(preset.fusion) <= set(models) and preset.fusion
                                    and test_of[preset.fusion[0]] is test_of[preset.fusion[1]]) else None
    order = [*(fuse or ()), *(k for k in preset.models if k not in (fuse or ()))]  # the fused pair first
    results, written = {}, 0
    for key, kinds in groups.items():  # models on one grid share items (fusion, pictures)
        plan = _plan(models, [k for k in order if k in kinds], fuse, class_names)
        plan.late_into = into if into and into.sender in kinds else None
        if devkit_available():
            plan.pools = {k: WorldPool(plan.models[k][0], plan.models[k][1].eval) for k in plan.late}
        accs = evaluate_models(plan, tests[key], examples=Examples(run.report / "examples",
                                                                   preset.examples if not written else 0))
        results.update({e.name: Result(e, acc.summary()) for e, acc in accs.items()})
        for kind, pool in plan.pools.items():  # the devkit's DetectionEval on an export of the test split
            results[kind].metrics["devkit_detection_eval"] = devkit_detection(
                run.data, "test", pool.document(class_names), run.report / kind)
        for kind, cov in plan.coverage.items():
            results[kind].coverage = cov.summary()
        written += len(plan.models) >= 2
    for name, path in (external or {}).items():
        test = next(iter(tests.values()))
        summary = score_results(read_coco_results(path, test.ds, image_index(test.ds, "all"), "test"), test,
                                next(iter(models.values()))[2].eval.match_ious).summary()
        results[name] = Result(Entry(name), summary)
    for kind, choice in late.items():
        results[late_fusion_name(kind)].late_choice = choice
    if into is not None:
        results[late_into_name(into.sender, into.ego)].late_choice = into_choice
    _measure(run, preset, models, chosen, test_of, results)
    run.results = results


def _plan(models: dict, group: list[str], fuse: tuple | None, class_names: list[str]) -> Comparison:
    """What the test split scores of one grid's models: each model, the own-view ablation of those that
    read other views, the late fusion of those with 3D detections, the coverage of those multi-view
    models that say where they query, the fusion pair if both are here."""
    built = {k: models[k][1] for k in group}
    return Comparison({k: models[k][1:] for k in group},
                      own_view=tuple(k for k in group if built[k].reads_other_views),
                      late=tuple(k for k in group if built[k].world_outputs),
                      fuse=fuse if fuse and fuse[0] in group else None,
                      coverage={k: CoverageAccumulator(class_names, stride=built[k].coverage_stride())
                                for k in group if built[k].coverage_text and built[k].reads_other_views})


def _measure(run: BenchRun, preset: BenchPreset, models: dict, chosen: dict, test_of: dict, results: dict) -> None:
    """What the test stage measures beyond the metrics: each model's threshold sweep on test (for
    information), its inference time and threads, its choice, the encoding ceiling, the feature bytes
    late fusion saves, the pose-noise sweep."""
    for kind, (_, m, c) in models.items():
        r = results[kind]
        r.test_sweep = _without_scenario_counts(threshold_sweep(m, c, test_of[kind], preset.conf_grid, preset.iou))
        r.inference_ms, r.inference_threads = inference_ms(m, c, test_of[kind]), torch.get_num_threads()
        r.choice, r.train_threads = chosen[kind], run.models[kind].training.get("threads")
        if r.choice is not None:  # where a user needing the hidden-recall target would operate it
            r.hidden_point = hidden_target_point(r.choice.val_sweep, r.test_sweep, preset.hidden_recall_target)
    for kind in (k for k in preset.models if models[k][1].reads_other_views):  # the multi-view kinds' ceilings
        (_, m, c), test = models[kind], test_of[kind]
        if m.encoding_ceiling:  # the kind says whether its decoding loses road users a perfect detector finds
            results[kind].encoding_ceiling = encoding_ceiling(m, test, c.eval)
    reader = next((k for k in preset.models if models[k][1].reads_other_views), None)
    for kind in preset.late_fusion:  # against what a multi-view model reads from another car
        source = reader or kind
        results[late_fusion_name(kind)].feature_bytes = models[source][1].feature_bytes(test_of[source][0])
    if preset.pose_noise_sweep:
        log(f"pose noise: sigma {', '.join(f'{s:g}' for s in preset.pose_noise_sweep)} (m and deg) on test")
        for kinds in _by_grid(models).values():
            if not any(models[k][1].reads_other_views for k in kinds):
                continue  # nothing here reads another car
            order = [k for k in preset.models if k in kinds]
            sweep = pose_noise_sweep(preset, {k: models[k][1:] for k in order}, test_of[order[0]],
                                     {n: r.as_json() for n, r in results.items()})
            for name, rows in sweep.items():
                if results[name].pose_noise_sweep is None:
                    results[name].pose_noise_sweep = rows
    _time_axis(run, preset, models, results)


def _time_axis(run: BenchRun, preset: BenchPreset, models: dict, results: dict) -> None:
    """The delay sweep and the tracks on the test sequences (``pnyolo.bench.time_axis``), if the preset asks."""
    from pnyolo.bench.time_axis import delay_sweep, tracking

    for kinds in _by_grid(models).values():
        order = {k: models[k][1:] for k in preset.models if k in kinds}
        if preset.delay_sweep and any(m.reads_other_views for m, _ in order.values()):
            log(f"delay: {', '.join(f'{d:g}' for d in preset.delay_sweep)} ms on the test sequences")
            for name, rows in delay_sweep(preset, order, run.data).items():
                if name in results and results[name].delay_sweep is None:
                    results[name].delay_sweep = rows
        if preset.tracking:
            log("tracking on the test sequences")
            for name, figures in tracking(preset, order, run.data).items():
                if name in results:
                    results[name].tracking = figures


def _by_grid(models: dict) -> dict[tuple, list[str]]:
    """The models (kind -> (path, model, config)) grouped by the grid their items are cut on
    (data.image_scale, data.cell_px): each group is scored on its own items, the ground truth the same."""
    groups: dict[tuple, list[str]] = {}
    for kind, (_, _, c) in models.items():
        groups.setdefault((c.data.image_scale, c.data.cell_px), []).append(kind)
    return groups
