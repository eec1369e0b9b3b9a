"""The benchmark's test stage: every model at the operating point chosen on validation, its predictions made
once per (split, condition) by the one prediction plan (``pnyolo.bench.plan``, the plan ``pnyolo-eval`` builds
from its flags), then scored with what the preset makes of them, each row a typed ``Result`` in ``run.results``::

    select_and_test(run)      # choose on validation (pnyolo.bench.selection), then score test
    run.results[kind].choice, run.results[late_fusion_name(kind)].metrics

What each model gets comes from its kind's decoding (``PredictionPlan.of``): the own-view ablation for kinds
that read other views, late fusion for kinds with 3D detections, the sampling coverage for kinds that say where they
query the world, the encoding ceiling for kinds with YOLO-grid targets; the fusion pair, the baseline
and the primary model are the preset's, and the first kind with 3D detections is also late-fused into the
baseline (``late_choice.choose_late_into``). The conditions: clean and own view on validation and test,
each pose-noise sigma on test, each delay on the test sequences (every camera, every frame: the delay-0 rows
and the tracks read the clean and own-view predictions of the whole sequences).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import torch

from dataset_spec import Dataset
from pnyolo.bench.late_choice import choose_late_fusion, choose_late_into
from pnyolo.bench.plan import PredictionPlan, predict_plan, predict_scoring
from pnyolo.bench.presets import BenchPreset
from pnyolo.bench.record import BenchRun, Result
from pnyolo.bench.robustness import pose_noise_sweep
from pnyolo.bench.selection import _without_layout_counts, choose_on_validation, hidden_target_point, threshold_sweep
from pnyolo.bench.stages import log
from pnyolo.cooperation.pose_noise import PoseNoise
from pnyolo.data.dataset import Delay, MultiViewDataset
from pnyolo.engine.predict import Trained, time_per_item
from pnyolo.evaluation.devkit_eval import available as devkit_available
from pnyolo.evaluation.devkit_eval import devkit_detection
from pnyolo.evaluation.evaluate import (Entry, Examples, LateInto, encoding_ceiling,
                                        evaluate_models, late_fusion_name, late_into_name)
from pnyolo.evaluation.nuscenes_results import WorldPool
from pnyolo.evaluation.predictions import image_index, read_coco_results, score_results


def select_and_test(run: BenchRun, external: dict[str, Path] | None = None) -> None:
    """Each model's checkpoint, batch-norm statistics, decoding settings and threshold chosen on
    validation, then every model and what the preset makes of them scored on test (``run.results``, the
    example pictures in the report folder). ``external``: other detectors' COCO results on the test split
    (every lighting variant, ids of the COCO export with --variant all), scored beside them."""
    preset = run.preset
    run.report.mkdir(parents=True, exist_ok=True)
    chosen, vals = {}, {}
    class_names = Dataset.open(run.data).info.detectable_classes
    for kind in preset.models:
        enc = getattr(run.models[kind].config.model, "encoder", None)
        paths = {"encoder.feature_cache": enc.feature_cache} if enc is not None and enc.feature_cache else None
        chosen[kind] = choose_on_validation(preset, run.data, run.runs, kind, class_names, vals, paths, run.device)
        run.models[kind].checkpoint = chosen[kind].trained.path
    log(f"chosen on the validation split (checkpoint, statistics, NMS IoU and depth gap: best F1@{preset.iou}; threshold: "
        "one-standard-error rule): " + ", ".join(f"{k} {v.checkpoint} ({v.eval_stats} statistics, NMS IoU "
                                                 f"{v.nms_iou or 'none'}, depth gap {v.depth_gap}) at confidence "
                                                 f"{v.threshold:.2f}" for k, v in ((k, c.choice) for k, c in chosen.items())))
    trained = {k: c.trained for k, c in chosen.items()}
    late, cars = {}, {}
    senders = [k for k in preset.late_fusion if trained[k].decoding.world_outputs]  # built with 3D detections
    for kind in senders:  # the late-fusion rule, chosen on validation like the models
        t = trained[kind]
        sent = PredictionPlan((kind,), late=(kind,), clean=False)  # what its cars send: each view alone
        cars[kind] = predict_plan(sent, trained, vals[_grid(t)]).models[kind].cars
        late[kind] = choose_late_fusion(preset, cars[kind], t.config)
        trained[kind] = replace(t, config=replace(t.config, eval=late[kind].point(t.config.eval)))  # a new point
        chosen[kind] = replace(chosen[kind], trained=trained[kind])
    groups = _by_grid(trained)
    tests = {key: MultiViewDataset(run.data, "test", trained[kinds[0]].config, training=False,
                                   every_camera=preset.every_camera) for key, kinds in groups.items()}
    test_of = {k: tests[key] for key, kinds in groups.items() for k in kinds}
    into, into_choice = None, None
    sender = preset.late_sender if preset.late_sender in senders else next(iter(senders), None)
    ego = preset.baseline
    if sender and ego in trained and ego != sender and test_of[sender] is test_of[ego]:
        into_choice = choose_late_into(preset, cars[sender], trained[sender].config, chosen[ego].val,
                                       trained[ego].config, ego)
        into = LateInto(sender, ego, into_choice.send, into_choice.ego_threshold)
    log(f"evaluate: {len(next(iter(tests.values())))} test items, "
        f"{preset.scored_text(next(iter(trained.values())).config.data.num_views)}")
    fuse = tuple(preset.fusion) if (set(preset.fusion) <= set(trained) and preset.fusion
                                    and test_of[preset.fusion[0]] is test_of[preset.fusion[1]]) else None
    order = [*(fuse or ()), *(k for k in preset.models if k not in (fuse or ()))]  # the fused pair first
    results, scorings, written = {}, {}, 0
    for key, kinds in groups.items():  # models on one grid share items (fusion, pictures)
        group = {k: trained[k].decoding for k in order if k in kinds}
        plan = PredictionPlan.of(group, fuse=fuse if fuse and fuse[0] in group else None,
                                 late_into=into if into and into.sender in kinds else None)
        comparison = predict_plan(plan, trained, tests[key])
        scorings.update(comparison.models)
        if devkit_available():
            comparison.pools = {k: WorldPool(trained[k].decoding, trained[k].config.eval, tests[key].ds)
                                for k in comparison.late}
        accs = evaluate_models(comparison, tests[key], examples=Examples(run.report / "examples",
                                                                         preset.examples if not written else 0))
        results.update({e.name: Result(e, acc.summary()) for e, acc in accs.items()})
        for kind, pool in comparison.pools.items():  # the devkit's DetectionEval on an export of the test split
            results[kind].metrics["devkit_detection_eval"] = devkit_detection(
                run.data, "test", pool.document(class_names), run.report / kind)
        for kind, cov in comparison.coverage.items():
            results[kind].coverage = cov.summary()
        written += len(comparison.models) >= 2
    for name, path in (external or {}).items():
        test = next(iter(tests.values()))
        summary = score_results(read_coco_results(path, test.ds, image_index(test.ds, "all"), "test"), test,
                                next(iter(trained.values())).config.eval.match_ious).summary()
        results[name] = Result(Entry(name), summary)
    for kind, choice in late.items():
        results[late_fusion_name(kind)].late_choice = choice
    if into is not None:
        results[late_into_name(into.sender, into.ego)].late_choice = into_choice
    _measure(run, preset, chosen, scorings, test_of, results)
    run.results = results


def _measure(run: BenchRun, preset: BenchPreset, chosen: dict, scorings: dict, test_of: dict, results: dict) -> None:
    """What the test stage measures beyond the metrics: each model's threshold sweep on test (for
    information, from its test predictions), its inference time and threads, its choice, the encoding ceiling,
    the feature bytes late fusion saves, the pose-noise sweep."""
    for kind, c in chosen.items():
        m, cfg, r = c.trained.model, c.trained.config, results[kind]
        r.test_sweep = _without_layout_counts(threshold_sweep(scorings[kind].clean, cfg.eval, preset.conf_grid,
                                                                preset.iou))
        r.inference_ms, r.inference_threads = time_per_item(m, test_of[kind], cfg.eval), torch.get_num_threads()
        r.choice, r.train_threads = c.choice, run.models[kind].training.get("threads")
        if r.choice is not None:  # where a user needing the hidden-recall target would operate it
            r.hidden_point = hidden_target_point(r.choice.val_sweep, r.test_sweep, preset.hidden_recall_target)
    trained = {k: c.trained for k, c in chosen.items()}
    for kind in (k for k in preset.models if trained[k].decoding.reads_other_views):  # the multi-view kinds' ceilings
        t = trained[kind]
        if t.model.encoding_ceiling:  # the kind says whether its decoding loses road users a perfect detector finds
            results[kind].encoding_ceiling = encoding_ceiling(t.model, test_of[kind], t.config.eval)
    reader = next((k for k in preset.models if trained[k].decoding.reads_other_views), None)
    for kind in (k for k in preset.late_fusion if late_fusion_name(k) in results):  # against a multi-view model's reads
        source = reader or kind
        results[late_fusion_name(kind)].feature_bytes = trained[source].model.feature_bytes(test_of[source][0])
    if preset.pose_noise_sweep:
        log(f"pose noise: sigma {', '.join(f'{s:g}' for s in preset.pose_noise_sweep)} (m and deg) on test")
        for kinds in _by_grid(trained).values():
            order = [k for k in preset.models if k in kinds]
            multi = [k for k in order if trained[k].decoding.reads_other_views]
            if not multi:
                continue  # nothing here reads another car
            test = test_of[order[0]]
            noisy = {sigma: _clean(PredictionPlan(tuple(multi), pose_noise=PoseNoise(sigma, sigma, 0)), trained, test)
                     for sigma in preset.pose_noise_sweep}
            sweep = pose_noise_sweep(preset, {k: scorings[k] for k in multi}, noisy, test,
                                     {n: r.as_json() for n, r in results.items()})
            for name, rows in sweep.items():
                if results[name].pose_noise_sweep is None:
                    results[name].pose_noise_sweep = rows
    _time_axis(run, preset, trained, results, (scorings, test_of))


def _time_axis(run: BenchRun, preset: BenchPreset, trained: dict, results: dict, tested: tuple[dict, dict]) -> None:
    """The delay sweep and the tracks on the test sequences (``pnyolo.bench.time_axis``), if the preset asks: the
    whole sequences (every camera, every frame) predicted clean and each view alone once (the test stage's
    predictions, ``tested`` = (kind -> Scoring, kind -> test dataset), where they are of the same items), each
    delay's items clean."""
    from pnyolo.bench.time_axis import delay_sweep, tracking

    if not (preset.delay_sweep or preset.tracking):
        return
    for kinds in _by_grid(trained).values():
        order = {k: trained[k] for k in preset.models if k in kinds}
        multi = [k for k, t in order.items() if t.decoding.reads_other_views]
        delays = preset.delay_sweep if multi else ()
        kept = [k for k, t in order.items() if t.decoding.world_outputs or k in multi or k == preset.baseline and delays]
        if not kept:
            continue
        sequences = _sequences(run, "test")  # the delay sweep and the tracks run on the split's sequences only
        if not sequences:
            log("delay and tracks: the test split holds no sequence")
            return
        whole = MultiViewDataset(run.data, "test", next(iter(order.values())).config, training=False,
                                 every_camera=True, scenarios=sequences)
        seen = {k: _whole(order[k], whole, k in multi or order[k].decoding.world_outputs, tested, k) for k in kept}
        if delays:
            log(f"delay: {', '.join(f'{d:g}' for d in delays)} ms on the test sequences")
            late = {}
            for d in delays:
                data = MultiViewDataset(run.data, "test", whole.cfg, training=False, every_camera=True,
                                        delay=Delay(d, max(delays)), scenarios=sequences)
                late[d] = (data, _clean(PredictionPlan(tuple(multi)), order, data))
            for name, rows in delay_sweep(preset, seen, whole, late).items():
                if name in results and results[name].delay_sweep is None:
                    results[name].delay_sweep = rows
        if preset.tracking:
            tracked = {k: s for k, s in seen.items() if s.decoding.world_outputs}
            val = _validation_sequences(run, {k: order[k] for k in tracked})
            log("tracking on the test sequences" + (", the tracker's point chosen on the validation sequences" if val
                                                    else " (validation holds no sequences: the default point)"))
            for name, figures in tracking(tracked, whole, run.data, run.report, val).items():
                if name in results:
                    results[name].tracking = figures


def _validation_sequences(run: BenchRun, trained: dict[str, Trained]) -> tuple | None:
    """The validation split's sequences (every camera, every frame) and each tracked model's predictions of them,
    clean and each view alone (the tracker's operating point is chosen on them); None where no validation scenario
    has more than one frame."""
    sequences = _sequences(run, "val")
    if not trained or not sequences:
        return None
    val = MultiViewDataset(run.data, "val", next(iter(trained.values())).config, training=False, every_camera=True,
                           scenarios=sequences)
    return val, {k: predict_scoring(t, val, own=True) for k, t in trained.items()}


def _sequences(run: BenchRun, split: str) -> list[str]:
    """``split``'s scenarios of more than one frame (the new layouts are single frames)."""
    ds = Dataset.open(run.data)
    return [s for s in ds.split(split) if ds.scenario(s).frames > 1]


def _whole(t: Trained, whole, own: bool, tested: tuple[dict, dict], kind: str):
    """``t``'s Scoring of the whole test sequences (``own``: each view alone too): the test stage's predictions of
    those items where it made them all (and each view alone if asked), made otherwise."""
    from pnyolo.cooperation.senders import OwnViews
    from pnyolo.evaluation.evaluate import Scoring

    done = tested[0][kind]
    if done.own is None and own:
        return predict_scoring(t, whole, own=own)
    try:  # Predictions.on: KeyError for an item the test stage did not predict
        own_preds = done.own.on(whole) if done.own is not None else None
        clean = done.clean.on(whole)
    except KeyError:
        return predict_scoring(t, whole, own=own)
    cars = OwnViews(own_preds, t.config.eval) if own_preds is not None and t.decoding.world_outputs else None
    return Scoring(t.config, clean, own_preds, cars)


def _clean(plan: PredictionPlan, trained: dict[str, Trained], dataset) -> dict:
    """Each model's clean predictions under ``plan`` (a sweep's condition), by name."""
    return {k: s.clean for k, s in predict_plan(plan, trained, dataset).models.items()}


def _grid(t: Trained) -> tuple:
    """The grid a model's items are cut on (data.image_scale, data.cell_px)."""
    return t.config.data.image_scale, t.config.data.cell_px


def _by_grid(trained: dict[str, Trained]) -> dict[tuple, list[str]]:
    """The models grouped by the grid their items are cut on: each group is scored on its own items, the ground
    truth the same."""
    groups: dict[tuple, list[str]] = {}
    for kind, t in trained.items():
        groups.setdefault(_grid(t), []).append(kind)
    return groups
